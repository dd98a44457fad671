"""Exported policies outside JAX: the ONNX model under onnxruntime, or the same network in numpy.

Both take raw observations ``(D,)`` or ``(B, D)`` and return the deterministic action in [-1, 1]
(normaliser, observation clip and network as in training; see ``train.export``).
"""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import numpy as np

from methd_jax.normalise import normalise

FORMAT = "methd-jax-policy/1"


class DeployError(ValueError):
    """A deployment folder or input that cannot be used (the message says why)."""


ROBOT_FOOTPRINT = (1.13, 0.91)
"""The base's footprint, length x width (m): a manifest must describe this robot."""
ROBOT_LIMITS = (3.0, 2.0)
"""The base's top linear speed (m/s) and yaw rate (rad/s): no command goes beyond them."""


def params_sha256(params_npz: str | Path) -> str:
    """SHA-256 over the arrays of a ``params.npz`` (names sorted, raw float32 bytes): stable across
    rewrites of the zip file."""
    digest = hashlib.sha256()
    with np.load(params_npz) as data:
        for k in sorted(data.files):
            digest.update(k.encode() + b"\0" + np.ascontiguousarray(data[k], np.float32).tobytes())
    return digest.hexdigest()


def load_manifest(path: str | Path) -> dict:
    """The manifest of a deployment folder written by ``python -m train.export``, refused with a
    :class:`DeployError` unless it can be trusted to drive this robot: readable, its parameters
    the ones it was exported with and its ONNX model the one written then (SHA-256 of each), its
    ray count the network's, its control rate, footprint and action scale those of the base."""
    path = Path(path)
    if (path / "deploy" / "manifest.json").exists():
        path = path / "deploy"
    file = path / "manifest.json"
    if not file.exists():
        raise DeployError(f"{path} holds no exported policy (manifest.json is missing)")
    try:
        manifest = json.loads(file.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise DeployError(f"{file}: not valid JSON ({e})") from None
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        got = manifest.get("format") if isinstance(manifest, dict) else None
        raise DeployError(f"{file}: unknown policy format {got!r}, expected {FORMAT!r}")
    if "deployment" not in manifest:
        raise DeployError(
            f"{path} is a training export without a deployment section; run `python -m train.export "
            f"{path.parent if path.name == 'policy' else path}` first"
        )
    try:
        _check(manifest, path)
    except (KeyError, TypeError, ValueError) as e:
        if isinstance(e, DeployError):
            raise
        raise DeployError(f"{file}: missing or malformed field ({type(e).__name__}: {e})") from None
    manifest["_dir"] = str(path)
    return manifest


def _check(manifest: dict, path: Path) -> None:
    """The checks of :func:`load_manifest` (KeyError / TypeError / ValueError on a malformed field)."""
    file = path / "manifest.json"
    try:
        digest = params_sha256(path / "params.npz")
    except FileNotFoundError:
        raise DeployError(f"{path / 'params.npz'} is missing") from None
    except Exception as e:  # a truncated or foreign zip: numpy and zipfile raise many kinds
        raise DeployError(f"{path / 'params.npz'}: unreadable ({type(e).__name__})") from None
    if digest != manifest.get("params_sha256"):
        raise DeployError(
            f"{path / 'params.npz'} does not match the manifest's params_sha256 (another run's?)"
        )
    onnx = path / manifest["onnx"]["file"]
    try:
        onnx_digest = hashlib.sha256(onnx.read_bytes()).hexdigest()
    except OSError:
        raise DeployError(f"{onnx} is missing or unreadable; re-run `python -m train.export`") from None
    if onnx_digest != manifest.get("onnx_sha256"):
        raise DeployError(f"{onnx} does not match the manifest's onnx_sha256 (altered or another run's?)")
    d = manifest["deployment"]
    hz = float(d["control_hz"])
    if not (math.isfinite(hz) and hz > 0):
        raise DeployError(f"{file}: control_hz must be positive, got {d['control_hz']!r}")
    if manifest["action"].get("frame") != "robot":  # not a base command: no robot to check against
        return
    rays = d["lidar"]["num_rays"]
    if manifest["network"].get("num_rays") != rays or manifest["observation_layout"]["lidar"] != [0, rays]:
        raise DeployError(f"{file}: lidar.num_rays {rays!r} disagrees with the network's observation")
    sectors = d["lidar"].get("clearance_sectors", 0)  # folders exported before the field had none
    field = manifest["observation_layout"].get("clearance")
    width = field[1] - field[0] if field else 0
    if not (isinstance(sectors, int) and sectors == width and (not sectors or rays % sectors == 0)):
        raise DeployError(
            f"{file}: lidar.clearance_sectors {sectors!r} disagrees with the observation's clearance "
            f"field ({width} values) or does not divide the {rays} rays"
        )
    if sectors and not d["lidar"].get("clearance_range", 0) > 0:
        raise DeployError(f"{file}: lidar.clearance_range must be positive metres")
    fp = d["footprint"]
    if not np.allclose([fp["length"], fp["width"]], ROBOT_FOOTPRINT, atol=1e-3):
        raise DeployError(
            f"{file}: footprint {fp['length']} x {fp['width']} m is not the base's "
            f"{ROBOT_FOOTPRINT[0]} x {ROBOT_FOOTPRINT[1]} m"
        )
    order = d.get("user_order", "fixed")  # folders exported before the field had a fixed order
    if order not in ("fixed", "goal"):
        raise DeployError(f"{file}: user_order {order!r} is neither 'fixed' nor 'goal'")
    if order == "goal":
        hip = d.get("hip")
        offsets = [hip.get(k) for k in ("distance", "lateral")] if isinstance(hip, dict) else [None]
        if not all(isinstance(v, int | float) and math.isfinite(v) for v in offsets):
            raise DeployError(f"{file}: user_order 'goal' needs hip.distance and hip.lateral in metres")
    scale = np.asarray(d["action"]["scale"], float)
    limit = np.array([ROBOT_LIMITS[0], ROBOT_LIMITS[0], ROBOT_LIMITS[1]])
    if scale.shape != (3,) or not np.all((scale > 0) & (scale <= limit + 1e-9)):
        raise DeployError(
            f"{file}: action.scale {d['action']['scale']} exceeds the base's limits {limit.tolist()}"
        )


def elu(x: np.ndarray) -> np.ndarray:
    return np.where(x > 0, x, np.expm1(np.minimum(x, 0.0)))


def conv1d(x: np.ndarray, kernel: np.ndarray, stride: int) -> np.ndarray:
    """Valid 1D convolution ``(B, L, Cin) x (k, Cin, Cout) -> (B, L', Cout)`` (Flax's layout)."""
    k = kernel.shape[0]
    n = (x.shape[1] - k) // stride + 1
    index = np.arange(n)[:, None] * stride + np.arange(k)[None]
    return np.einsum("bnkc,kco->bno", x[:, index, :], kernel, optimize=True)


class NumpyPolicy:
    """The exported network evaluated with numpy (no onnxruntime needed; float32 throughout), layer
    by layer as the manifest's ``deployment.policy_layers`` describes it (written by the network
    itself at export: ``networks.ActorCritic.policy_layers``)."""

    def __init__(self, manifest: dict):
        with np.load(Path(manifest["_dir"]) / "params.npz") as data:
            self.p = {k: data[k].astype(np.float32) for k in data.files}
        self.manifest = manifest
        self.clip = float(manifest["observation_clip"])
        self.layers = manifest["deployment"].get("policy_layers")
        if not isinstance(self.layers, dict) or self.layers.get("activation") != "elu":
            raise DeployError(
                f"{manifest['_dir']}: no ELU policy_layers in the deployment section; "
                "re-run `python -m train.export`"
            )
        names = [*self.layers["body"], self.layers["mean"]]
        if "encoder" in self.layers:
            enc = self.layers["encoder"]
            names += [c["params"] for c in enc["conv"]] + [enc["project"]]
        missing = sorted(n for n in names if f"{n}/kernel" not in self.p or f"{n}/bias" not in self.p)
        if missing:
            raise DeployError(f"{manifest['_dir']}: params.npz lacks the layers {missing} its manifest names")

    def _dense(self, x, name):
        return x @ self.p[f"{name}/kernel"] + self.p[f"{name}/bias"]

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        obs = np.asarray(obs, np.float32)
        single = obs.ndim == 1
        x = obs[None] if single else obs
        h = normalise(x, self.p["obs_mean"], self.p["obs_std"], self.clip)
        if "encoder" in self.layers:
            enc = self.layers["encoder"]
            rays = enc["input"]
            e = h[:, :rays, None]
            for conv in enc["conv"]:
                name = conv["params"]
                e = elu(conv1d(e, self.p[f"{name}/kernel"], conv["stride"]) + self.p[f"{name}/bias"])
            latent = elu(self._dense(e.reshape(e.shape[0], -1), enc["project"]))
            h = np.concatenate([latent, h[:, rays:]], -1)
        for name in self.layers["body"]:
            h = elu(self._dense(h, name))
        action = np.clip(self._dense(h, self.layers["mean"]), -1.0, 1.0).astype(np.float32)
        return action[0] if single else action


class OnnxPolicy:
    """``policy.onnx`` under onnxruntime on the CPU (one thread: latency, not throughput, matters)."""

    def __init__(self, manifest: dict, threads: int = 1):
        try:
            import onnxruntime as ort
        except ImportError:
            raise DeployError(
                "onnxruntime is not installed; `pip install onnxruntime` or use backend='numpy'"
            ) from None
        file = Path(manifest["_dir"]) / manifest.get("onnx", {}).get("file", "policy.onnx")
        if not file.exists():
            raise DeployError(f"{file} is missing; re-run `python -m train.export`")
        options = ort.SessionOptions()
        options.intra_op_num_threads = threads
        options.inter_op_num_threads = 1
        try:
            self.session = ort.InferenceSession(str(file), options, providers=["CPUExecutionProvider"])
        except Exception as e:  # onnxruntime raises its own exception types for a corrupt model
            raise DeployError(f"{file}: not a loadable ONNX model ({type(e).__name__})") from None
        size = self.session.get_inputs()[0].shape[-1]
        if size != manifest["observation_size"]:
            raise DeployError(f"{file} takes {size} inputs; the manifest says {manifest['observation_size']}")
        self.input = self.session.get_inputs()[0].name
        self.manifest = manifest

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        obs = np.asarray(obs, np.float32)
        single = obs.ndim == 1
        out = self.session.run(None, {self.input: obs[None] if single else obs})[0]
        return out[0] if single else out


def load_policy(path: str | Path, backend: str = "onnx"):
    """The policy of a deployment folder with ``backend`` "onnx" (onnxruntime) or "numpy"."""
    manifest = load_manifest(path)
    if backend == "onnx":
        return OnnxPolicy(manifest)
    if backend == "numpy":
        return NumpyPolicy(manifest)
    raise DeployError(f"unknown backend {backend!r}; use 'onnx' or 'numpy'")
