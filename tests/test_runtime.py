"""tomgs.runtime's descriptors: what a kernel reads through them is what the tensor holds."""

from __future__ import annotations

import pytest
import torch
import warp as wp

from scenes import devices
from tomgs.runtime import launch, scope, wrap, wrap_part


@wp.kernel
def _copy(src: wp.array(dtype=wp.int32), dst: wp.array(dtype=wp.int32)):
    i = wp.tid()
    dst[i] = src[i]


@wp.kernel
def _two_vectors(a: wp.vec3, b: wp.vec3, out: wp.array(dtype=wp.vec3)):
    out[0] = a
    out[1] = b


@pytest.mark.parametrize("device", devices())
def test_a_recorded_launch_keeps_each_vector_argument_apart(device):
    """A vector passed for two arguments of the first (recorded) launch: the command sets each one's value in
    place at later launches, so each must hold its own copy (else the last value set reached both), and the
    caller's vector keeps its value."""
    from tomgs.runtime import Launches

    fresh = Launches()
    out = torch.zeros(2, 3, device=device)
    one = wp.vec3(1.0, 1.0, 1.0)
    with scope(torch.device(device)) as wp_device:
        fresh(_two_vectors, 1, [one, one, wrap(out, wp.vec3)], wp_device)
        assert out.tolist() == [[1.0] * 3] * 2
        fresh(_two_vectors, 1, [wp.vec3(2.0, 3.0, 4.0), wp.vec3(5.0, 6.0, 7.0), wrap(out, wp.vec3)], wp_device)
    assert out.tolist() == [[2.0, 3.0, 4.0], [5.0, 6.0, 7.0]]
    assert list(one) == [1.0, 1.0, 1.0]


@wp.struct
class _Span:
    src: wp.array(dtype=wp.int32)
    offset: int
    scale: float


@wp.kernel
def _scaled_copy(span: _Span, dst: wp.array(dtype=wp.int32)):
    i = wp.tid()
    dst[i] = int(float(span.src[i + span.offset]) * span.scale)


@pytest.mark.parametrize("device", devices())
def test_a_recorded_launch_reads_each_calls_struct_and_leaves_the_callers_alone(device):
    """A struct argument (a `struct_values` value holding descriptors and scalars) is copied whole into the
    command's own value at every call: each call reads its own arrays and scalars, and the values passed
    before keep their bytes; another type in its place is refused."""
    from tomgs.runtime import Launches, struct_values

    fresh = Launches()
    span_values = struct_values(_Span)
    with scope(torch.device(device)) as wp_device:
        held = []
        for k in range(3):
            src = torch.arange(8, dtype=torch.int32, device=device) * (k + 1)
            dst = torch.zeros(5, dtype=torch.int32, device=device)
            span = span_values(src=wrap(src), offset=k, scale=float(k + 2))
            before = bytes(span)
            fresh(_scaled_copy, 5, [span, wrap(dst)], wp_device)
            expected = (torch.arange(k, k + 5, dtype=torch.int32) * (k + 1) * (k + 2)).tolist()
            assert dst.cpu().tolist() == expected
            held.append((src, dst, span, before))
        for _, _, span, before in held:
            assert bytes(span) == before
        with pytest.raises(TypeError, match="struct"):
            fresh(_scaled_copy, 5, [wrap(src), wrap(dst)], wp_device)


@pytest.mark.parametrize("device", devices())
def test_wrap_part_reads_and_writes_its_range_only(device):
    """A kernel sees elements [start, start + length) of the tensor, and writing through the part
    changes nothing outside it."""
    values = torch.arange(20, dtype=torch.int32, device=device)
    target = torch.full((20,), -1, dtype=torch.int32, device=device)
    with scope(values.device) as wp_device:
        launch(_copy, 6, device=wp_device, args=[wrap_part(values, 7, 6), wrap(target)])
        launch(_copy, 3, device=wp_device, args=[wrap(values), wrap_part(target, 15, 3)])
    expected = torch.full((20,), -1, dtype=torch.int32)
    expected[:6] = torch.arange(7, 13)
    expected[15:18] = torch.arange(3)
    assert torch.equal(target.cpu(), expected)


@pytest.mark.parametrize("start, length", [(-1, 2), (19, 2), (0, 21)])
def test_wrap_part_refuses_a_range_outside_the_tensor(start, length):
    with pytest.raises(ValueError, match="range of a contiguous 1D tensor"):
        wrap_part(torch.zeros(20, dtype=torch.int32), start, length)


def test_wrap_part_refuses_a_strided_or_2d_tensor():
    with pytest.raises(ValueError, match="contiguous 1D"):
        wrap_part(torch.zeros(20, dtype=torch.int32)[::2], 0, 2)
    with pytest.raises(ValueError, match="contiguous 1D"):
        wrap_part(torch.zeros(4, 5, dtype=torch.int32), 0, 2)


@pytest.mark.parametrize("device", devices())
def test_a_recorded_launch_reads_each_calls_arrays_and_leaves_theirs_alone(device):
    """Launches re-arms one recorded command per kernel: each call's arrays are copied into the
    command's own descriptors, so every call reads its own tensors, and the descriptors a caller
    passed before (NO_ARRAY, a frame's saved ones) keep pointing where they did."""
    from tomgs.runtime import NO_ARRAY, Launches

    fresh = Launches()
    empty_before = bytes(NO_ARRAY)
    with scope(torch.device(device)) as wp_device:
        held = []
        for k in range(3):
            src = torch.arange(5, dtype=torch.int32, device=device) * (k + 1)
            dst = torch.zeros(5, dtype=torch.int32, device=device)
            src_d, dst_d = wrap(src), wrap(dst)
            before = bytes(src_d), bytes(dst_d)
            fresh(_copy, 5, [src_d, dst_d], wp_device)
            assert torch.equal(dst.cpu(), torch.arange(5, dtype=torch.int32) * (k + 1))
            held.append((src, dst, src_d, dst_d, before))
        for _, _, src_d, dst_d, before in held:
            assert (bytes(src_d), bytes(dst_d)) == before
        with pytest.raises(TypeError, match="wrap"):
            fresh(_copy, 5, [wp.zeros(5, dtype=wp.int32, device=wp_device), wrap(dst)], wp_device)
    assert bytes(NO_ARRAY) == empty_before


def test_kernels_of_one_name_in_two_modules_keep_their_own_recorded_launches(tmp_path):
    """Launches records a command per kernel, not per kernel name: a kernel named like another
    module's (a benchmark importing an older copy of a module beside the current one) runs itself,
    with its own arguments, instead of re-arming the other's command."""
    import importlib.util

    from tomgs.runtime import Launches

    def module(name: str, body: str):
        path = tmp_path / f"{name}.py"
        path.write_text("import warp as wp\n\n\n@wp.kernel\ndef fill(out: wp.array(dtype=wp.int32)" + body)
        spec = importlib.util.spec_from_file_location(name, path)
        loaded = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(loaded)
        return loaded

    first = module("tomgs_test_fill_one", "):\n    out[wp.tid()] = 1\n")
    second = module("tomgs_test_fill_value", ", value: int):\n    out[wp.tid()] = value\n")
    fresh = Launches()
    out = torch.zeros(4, dtype=torch.int32)
    with scope(torch.device("cpu")) as wp_device:
        fresh(first.fill, 4, [wrap(out)], wp_device)
        assert out.tolist() == [1] * 4
        fresh(second.fill, 4, [wrap(out), 7], wp_device)
        assert out.tolist() == [7] * 4
        fresh(first.fill, 4, [wrap(out)], wp_device)
        assert out.tolist() == [1] * 4


def test_warps_quiet_start_silences_only_native_writes():
    """While Warp starts on a machine without CUDA, native code's writes to descriptor 2 go nowhere, but
    what Python writes to sys.stderr meanwhile, from this thread or another (a rank's first line while its
    warm-up thread starts Warp), reaches stderr: before, the redirect swallowed it and a two-rank fit said
    one rank's line only. Afterwards sys.stderr is what it was and descriptor 2 is stderr again."""
    import subprocess
    import sys
    import textwrap

    script = textwrap.dedent("""
        import os, sys, threading
        from tomgs.runtime import _native_stderr_silenced

        before = sys.stderr
        with _native_stderr_silenced():
            os.write(2, b"native line\\n")
            sys.stderr.write("python line\\n")
            other = threading.Thread(target=lambda: sys.stderr.write("thread line\\n") and sys.stderr.flush())
            other.start()
            other.join()
        assert sys.stderr is before
        os.write(2, b"after\\n")
    """)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stderr.splitlines() == ["python line", "thread line", "after"], done.stderr
