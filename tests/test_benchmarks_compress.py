"""benchmarks/compress.py runs end to end in its tiny CPU mode and reports what it says it reports."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_compress_benchmark_smoke(tmp_path):
    out = tmp_path / "report.json"
    done = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "compress.py"), "--smoke", "--out",
                           str(tmp_path / "work"), "--json", str(out)], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    report = json.loads(out.read_text())
    assert report["gaussians"] == 3000 and report["frames"] == 4
    assert 0 < report["output_bytes"] < report["input_bytes"]
    assert report["bits_per_pixel"] == 8 * report["output_bytes"] / (96 * 54 * 4)
    assert report["compress_seconds"] > 0 and report["load_seconds"] > 0
    assert set(report["image_bytes_per_gaussian"]) >= {"means_hi", "means_lo", "quats", "t_hi", "t_lo"}
    assert report["psnr_input"] > 40 and report["psnr_output"] > 35  # the clip is the input's own render
    assert (tmp_path / "work" / "smoke.tsog").is_file()
    assert "bits_per_pixel" in done.stdout and "psnr_output" in done.stdout
