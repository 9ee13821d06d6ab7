"""Per-frame cameras of a clip: poses, intrinsics, image size and frame times.

Conventions (docs/design.md): OpenCV axes (x right, y down, z forward); `c2w` maps camera to world;
frame 0 is the identity pose; K in pixels with pixel centres at +0.5 (pixel (i, j) is centred at
x = j + 0.5, y = i + 0.5); time t in [0, 1], frame k of n at t = k / (n - 1).

Arrays are numpy float64 (poses are estimated and stored in double precision); `viewmats` and
`Ks` hand out torch tensors for the renderer when asked for a device.

JSON schema (`Cameras.save` / `Cameras.load`), version 1:

    {
      "format": "tomgs-cameras", "version": 1,
      "width": W, "height": H,                   # image size in pixels
      "K": [[fx, 0, cx], [0, fy, cy], [0, 0, 1]],  # pixels, centres at +0.5
      "frames": [                                  # one entry per frame, in clip order
        {"index": 0, "time": 0.0, "c2w": [[...4 numbers...] x 4]},
        ...
      ]
    }

`index` is the frame number in the source video (after any range selection it need not start
at 0); `time` is the frame time in [0, 1].

Files are io's: `load`, `from_colmap` and `from_anycam` hand the reading to tomgs.io.cameras, imported
inside the method (this module sits on a lower floor than io, docs/design.md), which also writes
COLMAP text and nerfstudio's transforms.json.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tomgs.errors import InputError, short_repr
from tomgs.constants import MAX_SIDE
from tomgs.outputs import write_text

FORMAT = "tomgs-cameras"
VERSION = 1


def frame_times(n: int) -> np.ndarray:
    """float64 [n]: t = k / (n - 1); a single frame at t = 0."""
    return np.arange(n, dtype=np.float64) / max(n - 1, 1)


def intrinsics(focal: float, width: int, height: int) -> np.ndarray:
    """float64 [3, 3]: square pixels, principal point at the image centre (+0.5 convention)."""
    return np.array([[focal, 0.0, width / 2.0], [0.0, focal, height / 2.0], [0.0, 0.0, 1.0]])


def look_at(eye, target, up=(0.0, -1.0, 0.0)) -> np.ndarray:
    """float64 [4,4] camera-to-world of a camera at `eye` looking at `target` (OpenCV axes: the
    image's up is along `up`, by default world -y, since y points down)."""
    eye, target = np.asarray(eye, dtype=np.float64), np.asarray(target, dtype=np.float64)
    forward = target - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, np.asarray(up, dtype=np.float64))
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    c2w = np.eye(4)
    c2w[:3, :3] = np.stack([right, down, forward], axis=1)  # columns: camera axes in world coordinates
    c2w[:3, 3] = eye
    return c2w


MAX_FRAME_NUMBER = 2**31 - 1
"""Frame numbers are source frame numbers, stored as int32 in scene files."""


def _side(value, what: str) -> int:
    """An image side: an integer (not a bool) in 1..MAX_SIDE, else InputError."""
    try:
        ok = not isinstance(value, (bool, np.bool_, str, bytes)) and float(value) == int(value)
        side = int(value) if ok else None
    except (TypeError, ValueError, OverflowError):
        side = None
    if side is None or not 1 <= side <= MAX_SIDE:
        raise InputError(f"Cameras: {what} {short_repr(value)} is not a whole number of pixels in 1..{MAX_SIDE}")
    return side


def _frame_numbers(values) -> np.ndarray:
    """int64 [T] frame numbers in 0..MAX_FRAME_NUMBER, else InputError (never OverflowError)."""
    try:
        raw = np.asarray(values)
        if raw.dtype.kind == "f":
            if not (np.isfinite(raw).all() and (raw == np.round(raw)).all()):
                raise ValueError
        elif raw.dtype.kind == "O":  # Python ints too large for int64 (or anything else)
            raw = np.array([int(v) if isinstance(v, (int, np.integer)) and not isinstance(v, bool) else None
                            for v in raw.ravel()], dtype=object).reshape(raw.shape)
            if any(v is None or not 0 <= v <= MAX_FRAME_NUMBER for v in raw.ravel()):
                raise ValueError
        elif raw.dtype.kind not in "iub":
            raise ValueError
        if raw.size and (raw.min() < 0 or raw.max() > MAX_FRAME_NUMBER):
            raise ValueError
        return raw.astype(np.int64)
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"Cameras: every frame number (frame_indices) must be a whole number in "
                         f"0..{MAX_FRAME_NUMBER} (the source frame it came from)") from None


@dataclass
class Cameras:
    """c2w float64 [T,4,4]; K float64 [3,3]; width, height in pixels; times float64 [T] in [0,1];
    frame_indices int64 [T] (source frame numbers)."""

    c2w: np.ndarray
    K: np.ndarray
    width: int
    height: int
    times: np.ndarray
    frame_indices: np.ndarray

    def __post_init__(self):
        self.width, self.height = _side(self.width, "width"), _side(self.height, "height")
        try:
            self.c2w = np.asarray(self.c2w, dtype=np.float64)
            self.K = np.asarray(self.K, dtype=np.float64)
            self.times = np.asarray(self.times, dtype=np.float64)
        except (TypeError, ValueError, OverflowError) as e:
            raise InputError(f"Cameras: c2w, K and times must be arrays of numbers ({e})") from None
        T = len(self.c2w) if self.c2w.ndim else 0
        indices = _frame_numbers(self.frame_indices)
        if self.c2w.shape != (T, 4, 4) or self.K.shape != (3, 3) or self.times.shape != (T,) \
                or indices.shape != (T,):
            raise InputError(f"Cameras: expected c2w [T,4,4], K [3,3], times [T], frame_indices [T]; got "
                             f"{self.c2w.shape}, {self.K.shape}, {self.times.shape}, {indices.shape}")
        self.frame_indices = indices
        if not (np.isfinite(self.c2w).all() and np.isfinite(self.K).all()):
            raise InputError("Cameras: c2w and K must be finite")
        if not np.isfinite(self.times).all():
            k = int(np.flatnonzero(~np.isfinite(self.times))[0])
            raise InputError(f"Cameras: frame {k} has time {self.times[k]}; frame times must be finite numbers in [0, 1]")
        bottom = np.abs(self.c2w[:, 3] - [0.0, 0.0, 0.0, 1.0]).max(axis=1) if T else np.zeros(0)
        if (bottom > 1e-6).any():
            k = int(np.argmax(bottom > 1e-6))
            raise InputError(f"Cameras: c2w of frame {k} has bottom row {self.c2w[k, 3].tolist()}; a camera-to-world "
                             "matrix ends in [0, 0, 0, 1]")
        if T:  # the rotation part must be invertible: relative to its largest, the smallest singular value
            s = np.linalg.svd(self.c2w[:, :3, :3], compute_uv=False)  # [T,3], descending
            bad = ~(s[:, 2] > 1e-9 * s[:, 0])
            if bad.any():
                k = int(np.argmax(bad))
                raise InputError(f"Cameras: c2w of frame {k} is singular (its 3x3 rotation part has singular values "
                                 f"{s[k].tolist()}); give a rotation and a translation")
        fx, fy = self.K[0, 0], self.K[1, 1]
        if not (fx > 0 and fy > 0):
            raise InputError(f"Cameras: focal lengths fx = {fx}, fy = {fy}; both must be positive (pixels)")
        if np.abs(self.K[2] - [0.0, 0.0, 1.0]).max() > 1e-9 or self.K[1, 0] != 0:
            raise InputError(f"Cameras: K = {self.K.tolist()} is not [[fx, s, cx], [0, fy, cy], [0, 0, 1]]")

    @classmethod
    def create(cls, c2w, K, width: int, height: int, frame_indices=None) -> "Cameras":
        """Cameras with times k/(n-1) and indices 0..T-1 unless given."""
        T = len(c2w)
        idx = np.arange(T) if frame_indices is None else frame_indices
        return cls(c2w, K, width, height, frame_times(T), idx)

    @classmethod
    def identity(cls, n: int, K, width: int, height: int, frame_indices=None) -> "Cameras":
        """n frames of a fixed camera."""
        return cls.create(np.tile(np.eye(4), (n, 1, 1)), K, width, height, frame_indices)

    def __len__(self) -> int:
        return len(self.c2w)

    def __getitem__(self, key) -> "Cameras":
        """Subset of frames (int, slice, index array or bool mask); times are kept, not renumbered."""
        if isinstance(key, (int, np.integer)):
            key = [int(key)]
        return Cameras(self.c2w[key], self.K.copy(), self.width, self.height, self.times[key],
                       self.frame_indices[key])

    @property
    def focal(self) -> float:
        return float((self.K[0, 0] + self.K[1, 1]) / 2)

    def viewmats(self, device=None):
        """World-to-camera [T,4,4] (what the rasterizer takes): numpy float64, or torch float32 on
        `device` when one is given."""
        w2c = np.linalg.inv(self.c2w)
        if device is None:
            return w2c
        import torch

        return torch.as_tensor(w2c, dtype=torch.float32, device=device)

    def Ks(self, device=None):
        """K repeated per frame [T,3,3]: numpy float64, or torch float32 on `device`."""
        Ks = np.broadcast_to(self.K, (len(self), 3, 3)).copy()
        if device is None:
            return Ks
        import torch

        return torch.as_tensor(Ks, dtype=torch.float32, device=device)

    def resized(self, width: int, height: int) -> "Cameras":
        """The same cameras for images resized to width x height (K scaled; +0.5 centres keep
        cx = sx * cx exactly)."""
        sx, sy = width / self.width, height / self.height
        K = self.K.copy()
        K[0] *= sx
        K[1] *= sy
        return Cameras(self.c2w.copy(), K, width, height, self.times.copy(), self.frame_indices.copy())

    def rebased(self) -> "Cameras":
        """Re-anchored so that frame 0 is the identity: c2w_k <- inv(c2w_0) @ c2w_k."""
        c2w = np.linalg.inv(self.c2w[0]) @ self.c2w
        return Cameras(c2w, self.K.copy(), self.width, self.height, self.times.copy(), self.frame_indices.copy())

    # ---- files ---------------------------------------------------------------------------------

    def to_dict(self) -> dict:
        return {
            "format": FORMAT,
            "version": VERSION,
            "width": self.width,
            "height": self.height,
            "K": self.K.tolist(),
            "frames": [{"index": int(i), "time": float(t), "c2w": m.tolist()}
                       for i, t, m in zip(self.frame_indices, self.times, self.c2w)],
        }

    @classmethod
    def from_dict(cls, d: dict, source="<dict>") -> "Cameras":
        fix = "see the schema in tomgs.cameras, or write the file with Cameras.save"
        if not isinstance(d, dict) or d.get("format") != FORMAT:
            raise InputError(f"{source} is not a tomgs cameras file (missing \"format\": \"{FORMAT}\")")
        if d.get("version") != VERSION:
            raise InputError(f"{source} has cameras version {short_repr(d.get('version'))}; this tomgs reads version "
                             f"{VERSION}")
        try:
            frames = d["frames"]
            if not isinstance(frames, list) or not all(isinstance(f, dict) for f in frames):
                raise TypeError("'frames' must be a list of objects")
            if not frames:
                raise InputError(f"{source} holds zero frames")
            return cls(np.array([f["c2w"] for f in frames]), np.array(d["K"]), d["width"], d["height"],
                       np.array([f["time"] for f in frames]), np.array([f["index"] for f in frames], dtype=object))
        except InputError as e:
            message = str(e)
            raise InputError(message if message.startswith(str(source)) else
                             f"{source}: {message.removeprefix('Cameras: ')}; {fix}") from None
        except (KeyError, TypeError, ValueError, OverflowError, RecursionError, IndexError) as e:
            raise InputError(f"{source} does not follow the tomgs cameras schema ({type(e).__name__}: "
                             f"{str(e)[:200]}); {fix}") from None

    def to_json(self) -> str:
        """The cameras file's text (`save` writes it, `load` reads it)."""
        return json.dumps(self.to_dict(), indent=1)

    def save(self, path) -> Path:
        """Write JSON atomically (temporary file in the same folder, then rename)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        return write_text(path, self.to_json())

    @classmethod
    def load(cls, path) -> "Cameras":
        """Read a cameras JSON file (InputError naming the file for anything it holds)."""
        from tomgs.io.cameras import load_json

        path = Path(path)
        if not path.is_file():
            raise InputError(f"cameras file {path} does not exist" + (" (it is a folder)" if path.is_dir() else ""))
        return cls.from_dict(load_json(path, "write it with Cameras.save"), path)

    @classmethod
    def from_anycam(cls, c2w, K, width: int, height: int) -> "Cameras":
        """AnyCam output: c2w [T,4,4] camera-to-world in OpenCV axes (array or .npy path) and K
        [3,3] or [T,3,3] in pixels (array or .npy/.txt path; per-frame K are averaged). Scale is
        kept as given; poses are re-anchored so that frame 0 is the identity."""
        from tomgs.io.cameras import read_anycam

        c2w, K, source = read_anycam(c2w, K)
        try:
            return cls.create(c2w, K, width, height).rebased()
        except InputError as e:
            raise InputError(f"{source}: {str(e).removeprefix('Cameras: ')}") from None

    def frame_names(self) -> list[str]:
        """The image name of each frame as `tomgs render -o folder/` writes it: '00012.png'."""
        return [f"{int(i):05d}.png" for i in self.frame_indices]

    @classmethod
    def from_colmap(cls, folder) -> "Cameras":
        """A COLMAP text model (folder with cameras.txt and images.txt; one shared camera), its
        images in name order (tomgs.io.cameras.read_colmap), re-anchored so that frame 0 is the
        identity. COLMAP already puts pixel centres at +0.5."""
        from tomgs.io.cameras import read_colmap

        c2w, K, w, h = read_colmap(folder)
        try:
            return cls.create(c2w, K, w, h).rebased()
        except InputError as e:
            raise InputError(f"{folder}: {str(e).removeprefix('Cameras: ')}") from None
