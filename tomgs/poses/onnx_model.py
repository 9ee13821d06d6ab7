"""Run a feed-forward pose model exported to ONNX (AnyCam's convention) with onnxruntime.

Contract (what a model must look like to be used with `method="model.onnx"`):

- one input, float32 [T, 3, H, W]: the clip's RGB frames in [0, 1] at their size in tomgs
  (models that need a fixed size should resize inside the graph);
- an output named "c2w", float32/64 [T, 4, 4]: camera-to-world per frame, OpenCV axes
  (x right, y down, z forward); frame 0 should be the identity (poses are re-anchored if not);
  any scale;
- an output named "K", [3, 3] or [T, 3, 3] (averaged over frames): intrinsics in pixels of
  the input frames, pixel centres at +0.5.

If the outputs are unnamed, a model with exactly two outputs shaped like the above is accepted
in the order (c2w, K). Anything else raises InputError saying what was found.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tomgs.cameras import Cameras
from tomgs.errors import InputError


def run_onnx(path, frames: np.ndarray, indices=None) -> Cameras:
    """frames uint8 [T,H,W,3] -> Cameras from the model at `path` (see the module contract)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"ONNX model {path} does not exist")
    try:
        import onnxruntime as ort
    except ImportError:
        raise InputError(f"{path}: running an ONNX pose model needs onnxruntime, an optional extra: "
                         f"pip install 'tomgs[onnx]'") from None
    try:
        sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    except Exception as e:  # onnxruntime raises its own exception types for bad files
        raise InputError(f"cannot load ONNX model {path}: {e}") from None
    inputs = sess.get_inputs()
    if len(inputs) != 1:
        raise InputError(f"{path} has {len(inputs)} inputs; the pose contract wants one: frames [T,3,H,W]")
    T, H, W = frames.shape[:3]
    x = np.ascontiguousarray(frames.transpose(0, 3, 1, 2), dtype=np.float32) / 255.0
    try:
        outs = sess.run(None, {inputs[0].name: x})
    except Exception as e:
        raise InputError(f"{path} failed on frames [T,3,H,W] = {list(x.shape)}: {e}") from None
    names = [o.name for o in sess.get_outputs()]
    got = ", ".join(f"{n} {list(np.shape(o))}" for n, o in zip(names, outs))
    byname = dict(zip(names, outs))
    if "c2w" in byname and "K" in byname:
        c2w, K = byname["c2w"], byname["K"]
    elif len(outs) == 2:
        c2w, K = outs
    else:
        raise InputError(f"{path} outputs {got}; the pose contract wants c2w [T,4,4] and K [3,3] "
                         "(see tomgs.poses.onnx_model)")
    c2w, K = np.asarray(c2w, np.float64), np.asarray(K, np.float64)
    if c2w.shape != (T, 4, 4):
        raise InputError(f"{path} outputs {got}: c2w must be [T,4,4] with T = {T} frames")
    if K.shape == (T, 3, 3):
        K = K.mean(0)
    if K.shape != (3, 3):
        raise InputError(f"{path} outputs {got}: K must be [3,3] or [T,3,3]")
    if not (np.isfinite(c2w).all() and np.isfinite(K).all()) or K[0, 0] <= 0 or K[1, 1] <= 0 \
            or abs(np.linalg.det(c2w[0, :3, :3])) < 1e-6:
        raise InputError(f"{path} outputs non-finite or singular poses, or a non-positive focal length")
    return Cameras.create(c2w, K, W, H, indices).rebased()
