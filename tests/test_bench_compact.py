"""benchmarks/compact.py's CPU smoke mode: a tiny clip fitted at two quality levels, each row with the
Gaussians and the scene file's bytes beside PSNR and SSIM."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_the_compact_benchmark_reports_size_beside_error(tmp_path):
    done = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "compact.py"), "--smoke", "--minutes", "0.2",
                           "--out", str(tmp_path)], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    rows = json.loads((tmp_path / "compact.json").read_text())
    assert [r["quality"] for r in rows] == ["default", "max"]
    for r in rows:
        scene = tmp_path / f"demo-{r['quality']}.ply"
        assert r["scene_bytes"] == scene.stat().st_size and r["gaussians"] > 0 and r["psnr"] > 10
        assert 0 < r["ssim"] <= 1 and r["curve"] and r["curve"][-1][1] == r["gaussians"]
        assert r["psnr_300s"] is None  # past the fit's end: no figure
    table = (tmp_path / "compact.md").read_text()
    assert "| demo | default |" in table and "scene_bytes" in table
