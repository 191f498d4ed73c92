"""The full VVLoc network: images of a rig → BEV → polar BEV → global + local descriptors."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError
from safetensors.torch import load as load_safetensors
from safetensors.torch import save
from torch import Tensor, nn

from vvloc._io import write_together
from vvloc.checkpoints import CONFIG_FILE, WEIGHTS_FILE, check_checkpoint_files
from vvloc.data.frame import PINHOLE, RIGID, Camera, is_pinhole, is_rigid
from vvloc.nets.backbone import FPN, ResNetBackbone, normalise_images
from vvloc.nets.config import CONFIG_VERSION, ModelConfig
from vvloc.nets.decoder import Interactor, LocalViewDecoder
from vvloc.nets.encoder import BevEncoder
from vvloc.nets.heads import make_global_head
from vvloc.nets.polar import polar_sample
from vvloc.provenance import TRAINING_FILE, read_record, record_json

#: Optional acceptance calibration of a checkpoint (see :func:`vvloc.localize.calibrate`).
CALIBRATION_FILE = "calibration.json"


def resolve_device(name: str | torch.device = "cpu", *, argument: str = "device") -> torch.device:
    """The torch device a model runs on: ``"cpu"``, ``"cuda"`` / ``"cuda:N"`` (refused with a
    ``ValueError`` naming ``argument`` when torch sees no such device), or ``"auto"`` (CUDA
    when available, else CPU). Apple's ``"mps"`` is refused: the encoder's camera geometry and
    the padding's shifts run in float64, which MPS does not have."""
    if isinstance(name, torch.device):
        dev = name
    elif isinstance(name, str):
        if name == "auto":
            return torch.device("cuda" if torch.cuda.is_available() else "cpu")
        try:
            dev = torch.device(name)
        except RuntimeError:
            dev = None
    else:
        raise TypeError(f"{argument}: expected a str or torch.device, got {type(name).__name__}")
    if dev is not None and dev.type == "mps":
        raise ValueError(
            f"{argument}: 'mps' is not supported (the camera geometry and the padding run in "
            "float64, which MPS lacks); use 'cpu'"
        )
    if dev is None or dev.type not in ("cpu", "cuda"):
        raise ValueError(f"{argument}: expected 'cpu', 'cuda', 'cuda:N' or 'auto', got {name!r}")
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(f"{argument}: {str(dev)!r} asked for, but torch sees no CUDA device")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ValueError(
                f"{argument}: {str(dev)!r} asked for, but torch sees "
                f"{torch.cuda.device_count()} CUDA device(s)"
            )
    return dev


def calibration_json(cal: dict[str, Any]) -> str:
    """``calibration.json``'s text: strict JSON, a non-finite number written as ``null``
    (a calibration that no threshold satisfies has ``min_distinctiveness`` = +inf, accept
    nothing, and ``precision`` = NaN; :func:`calibration_from_json` reads them back)."""

    def finite(v: Any) -> Any:
        if isinstance(v, float) and not math.isfinite(v):
            return None
        if isinstance(v, dict):
            return {k: finite(x) for k, x in v.items()}
        if isinstance(v, list):
            return [finite(x) for x in v]
        return v

    return json.dumps(finite(cal), indent=2, allow_nan=False)


def _hash_as_written(config: dict[str, Any]) -> str:
    """The config hash of vvloc before 2026-12-05, which hashed a config's numbers as they
    were written (15 and 15.0 apart): the canonical JSON of the dict as stored."""
    return hashlib.sha256(json.dumps(config, sort_keys=True).encode()).hexdigest()[:16]


def _check_calibration(cal: dict[str, Any], path: Path) -> dict[str, Any]:
    """``calibration.json``'s fields that the localizer reads, checked (``ValueError`` naming
    the file and the field): ``min_distinctiveness`` a number >= 0 or null (accept nothing),
    ``top_k`` an int >= 1 and ``accept_threshold`` a number, where present."""

    def number(v: Any) -> bool:
        return not isinstance(v, bool) and isinstance(v, (int, float))

    value = cal.get("min_distinctiveness", 0.0)
    if value is not None and not (number(value) and value >= 0):
        raise ValueError(
            f"{path}: min_distinctiveness must be a number >= 0 or null (accept nothing), got "
            f"{value!r}"
        )
    top_k = cal.get("top_k")
    if top_k is not None and (isinstance(top_k, bool) or not isinstance(top_k, int) or top_k < 1):
        raise ValueError(f"{path}: top_k must be an int >= 1, got {top_k!r}")
    threshold = cal.get("accept_threshold")
    if threshold is not None and not (number(threshold) and not math.isnan(threshold)):
        raise ValueError(f"{path}: accept_threshold must be a number, got {threshold!r}")
    return cal


def calibration_from_json(cal: dict[str, Any]) -> dict[str, Any]:
    """The calibration of :func:`calibration_json`'s text (``json.loads``'d): a ``null``
    ``min_distinctiveness`` is +inf (no threshold reached the target: accept nothing) and a
    ``null`` ``precision`` NaN."""
    out = dict(cal)
    if "min_distinctiveness" in out and out["min_distinctiveness"] is None:
        out["min_distinctiveness"] = math.inf
    if "precision" in out and out["precision"] is None:
        out["precision"] = math.nan
    return out


CHECKPOINT_FORMAT = "vvloc.nets.VVLocNet"


def _json_object(path: Path) -> dict[str, Any]:
    """The JSON object in ``path``; ``ValueError`` naming the file when it is not one."""
    try:
        value = json.loads(path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as e:  # too deep nesting
        raise ValueError(f"{path}: not a JSON file ({e})") from None
    if not isinstance(value, dict):
        raise ValueError(f"{path}: expected a JSON object, got {type(value).__name__}")
    return value


@dataclass
class EncoderOutput:
    """What :meth:`VVLocNet.encode` returns (in the model's dtype, float32 unless the model was
    converted, on the model's device).

    bev (B, H, W, C) channels-last; polar (B, T, R, C); global_desc (B, Dg) L2-normalised;
    local_desc (B, T, C) (not normalised; the interactor normalises its outputs).
    """

    bev: Tensor
    polar: Tensor
    global_desc: Tensor
    local_desc: Tensor


class VVLocNet(nn.Module):
    """VVLoc networks (DESIGN.md §1): BEV encoder, polar transform, global head, local-view
    decoder and interactor, built from a :class:`ModelConfig`."""

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        if not isinstance(config, ModelConfig):
            raise TypeError(f"config: expected a ModelConfig, got {type(config).__name__}")
        self.config = config
        #: Acceptance calibration (``{"min_distinctiveness": …, …}``), saved and loaded with the
        #: checkpoint as ``calibration.json``; empty when the model was never calibrated.
        self.calibration: dict[str, object] = {}
        #: Training record (:mod:`vvloc.provenance`: ``{"runs": [...]}``, the runs that produced
        #: these weights), saved and loaded as ``training.json``; empty when none was recorded.
        self.training_record: dict[str, Any] = {}
        self.backbone = ResNetBackbone(config.backbone_widths, config.backbone_blocks)
        self.fpn = FPN(config.backbone_widths, config.channels, config.num_levels)
        self.encoder = BevEncoder(config)
        self.global_head = make_global_head(config)
        self.decoder = LocalViewDecoder(config)
        self.interactor = Interactor(config)

    @property
    def global_dim(self) -> int:
        """Dg, the length of the global descriptor."""
        return int(self.global_head.out_dim)  # type: ignore[arg-type]

    def config_hash(self) -> str:
        """Stable hash of the architecture (the config's canonical JSON)."""
        return self.config.config_hash()

    def weights_hash(self) -> str:
        """SHA-256 (64 hex digits) of the weights: every state-dict entry in name order, with
        its name, dtype, shape and raw bytes (little-endian on the platforms vvloc builds for).
        Two trained models of one architecture share :meth:`config_hash` but not this; maps
        record it so that a map is only used with the weights that built it. Computed afresh
        on each call (the weights may change)."""
        h = hashlib.sha256()
        for name, tensor in sorted(self.state_dict().items()):
            t = tensor.detach().cpu().contiguous()
            h.update(f"{name}|{t.dtype}|{tuple(t.shape)}|".encode())
            h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
        return h.hexdigest()

    @property
    def training_rigs(self) -> list[list[Camera]] | None:
        """The rigs (each its cameras in image order) that these weights were last trained on:
        those of the last run of :attr:`training_record` that records them (``runs[].rigs``,
        written by ``vvloc train`` since 2026-12-05; several when its extra datasets had other
        cameras). After a fine-tuning on another rig that is the new rig alone. None when no
        run records one (weights from outside a run, or from an earlier vvloc)."""
        runs = self.training_record.get("runs") if isinstance(self.training_record, dict) else None
        for run in reversed(runs if isinstance(runs, list) else []):
            rigs = run.get("rigs") if isinstance(run, dict) else None
            if rigs:
                return [[Camera.from_json(c) for c in rig] for rig in rigs]
        return None

    # --- forward pieces --------------------------------------------------------------------

    def image_features(self, images: Tensor) -> list[Tensor]:
        """images (B, M, 3, Hi, Wi) uint8 or float in [0, 1] → FPN levels (B, M, C, H_l, W_l)."""
        b, m = images.shape[:2]
        x = normalise_images(images.flatten(0, 1)).to(self.encoder.queries.dtype)
        return [f.unflatten(0, (b, m)) for f in self.fpn(self.backbone(x))]

    def bev_from_features(
        self,
        feats: list[Tensor],
        intrinsics: Tensor,
        cam_to_ego: Tensor,
        image_size: tuple[int, int],
    ) -> Tensor:
        """FPN levels (B, M, C, H_l, W_l) + calibration → BEV (B, H, W, C)."""
        return self.encoder(feats, intrinsics, cam_to_ego, image_size)

    def polar(self, bev: Tensor) -> Tensor:
        """BEV (B, H, W, C) of the config's sizes and the model's dtype → polar BEV
        (B, T, R, C) (differentiable, DESIGN.md §3). ``ValueError``/``TypeError`` naming
        ``bev`` otherwise (another grid would be sampled at the wrong radii)."""
        cfg = self.config
        want = (cfg.bev_height, cfg.bev_width, cfg.channels)
        self._check_dtype(bev, "bev")
        if bev.ndim != 4 or tuple(bev.shape[1:]) != want:
            raise ValueError(
                f"bev: expected shape (B, {', '.join(map(str, want))}), got {tuple(bev.shape)}"
            )
        return polar_sample(bev, cfg.num_angles, cfg.num_radii, cfg.grid_size)

    def _check_dtype(self, x: Any, name: str) -> None:
        """``TypeError`` naming ``name`` unless ``x`` is a tensor of the model's dtype."""
        if not isinstance(x, Tensor):
            raise TypeError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
        if x.dtype != self.encoder.queries.dtype:
            raise TypeError(
                f"{name}: expected {self.encoder.queries.dtype} (the model's dtype), got {x.dtype}"
            )

    def encode(self, images: Tensor, intrinsics: Tensor, cam_to_ego: Tensor) -> EncoderOutput:
        """Encode one frame per batch item.

        images (B, M, 3, Hi, Wi) uint8 [0, 255] or float [0, 1], B, M >= 1; intrinsics
        (B, M, 3, 3) pinhole matrices in pixels of these images; cam_to_ego (B, M, 4, 4) rigid
        OpenCV camera → ego (x forward, y left, z up), metres. Calibration may differ per batch
        item. ``ValueError``/``TypeError`` naming the argument otherwise.
        """
        images, intrinsics, cam_to_ego = self._check_inputs(images, intrinsics, cam_to_ego)
        feats = self.image_features(images)
        size = (int(images.shape[-2]), int(images.shape[-1]))
        bev = self.bev_from_features(feats, intrinsics, cam_to_ego, size)
        polar = self.polar(bev)
        return EncoderOutput(
            bev=bev,
            polar=polar,
            global_desc=self.global_head(polar),
            local_desc=self.decoder(polar),
        )

    def decode_polar(self, polar: Tensor) -> Tensor:
        """Polar BEVs (N, T, R, C) of the model's dtype (e.g. of padded hypotheses) → local
        descriptors (N, T, C)."""
        self._check_dtype(polar, "polar")
        return self.decoder(polar)

    def interact(self, local_src: Tensor, local_tgt: Tensor) -> tuple[Tensor, Tensor]:
        """Local-view descriptor pairs (P, T, C) of the model's dtype and channels → (Ds', Dt')
        (P, T, C), rows L2-normalised."""
        self._check_dtype(local_src, "local_src")
        self._check_dtype(local_tgt, "local_tgt")  # the interactor checks their shapes
        return self.interactor(local_src, local_tgt)

    def _check_inputs(
        self, images: Tensor, intrinsics: Tensor, cam_to_ego: Tensor
    ) -> tuple[Tensor, Tensor, Tensor]:
        for name, x in (("images", images), ("intrinsics", intrinsics), ("cam_to_ego", cam_to_ego)):
            if not isinstance(x, Tensor):
                raise TypeError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
        if images.ndim != 5 or images.shape[2] != 3:
            raise ValueError(f"images: expected shape (B, M, 3, Hi, Wi), got {tuple(images.shape)}")
        if images.dtype != torch.uint8 and not images.is_floating_point():
            raise TypeError(f"images: expected uint8 or float, got {images.dtype}")
        b, m = images.shape[:2]
        if tuple(intrinsics.shape) != (b, m, 3, 3):
            raise ValueError(
                f"intrinsics: expected shape ({b}, {m}, 3, 3), got {tuple(intrinsics.shape)}"
            )
        if tuple(cam_to_ego.shape) != (b, m, 4, 4):
            raise ValueError(
                f"cam_to_ego: expected shape ({b}, {m}, 4, 4), got {tuple(cam_to_ego.shape)}"
            )
        if b == 0 or m == 0:
            raise ValueError(
                f"images: expected at least one frame (B >= 1) of at least one camera (M >= 1), "
                f"got shape {tuple(images.shape)}"
            )
        self.config.check_num_cameras(m)
        if images.is_floating_point():  # one reduction each; a sync on a GPU
            if not bool(torch.isfinite(images).all()):
                raise ValueError("images: holds non-finite values (NaN or inf)")
            lo, hi = float(images.min()), float(images.max())
            if lo < 0.0 or hi > 1.0:
                raise ValueError(
                    f"images: float images must lie in [0, 1], got values in [{lo:g}, {hi:g}] "
                    "(pass uint8 for the 0-255 scale)"
                )
        # a camera with bad calibration sees no BEV cell: its frame would encode as "no image"
        if not is_pinhole(intrinsics.detach().cpu().double().numpy()):
            raise ValueError(f"intrinsics: expected a {PINHOLE} for every camera")
        if not is_rigid(cam_to_ego.detach().cpu().double().numpy()):
            raise ValueError(f"cam_to_ego: expected a {RIGID} for every camera")
        dev, dtype = self.encoder.queries.device, self.encoder.queries.dtype
        return (
            images.to(dev),
            intrinsics.to(dev, dtype),
            cam_to_ego.to(dev, dtype),
        )

    # --- checkpoints -----------------------------------------------------------------------

    def save(self, directory: str | os.PathLike[str]) -> Path:
        """Write ``model.safetensors``, ``config.json`` (format, version, config, its hash and
        the weights' :meth:`weights_hash`, which :meth:`load` checks), when
        the model is calibrated ``calibration.json``, and when it has a training record
        ``training.json`` (:mod:`vvloc.provenance`, stamped with :meth:`weights_hash`) into
        ``directory`` (created if needed).
        Every file is serialised first, then all are written to temporaries and flushed before
        the first is renamed over its destination (:func:`vvloc._io.write_together`): a
        failure or interrupt leaves the folder's previous checkpoint whole, never new weights
        beside an old config or calibration. Only float32 models are saved (``TypeError``
        otherwise: load returns float32)."""
        runs = self.training_record.get("runs") if isinstance(self.training_record, dict) else None
        if self.training_record and not isinstance(runs, list):
            raise TypeError(
                "training_record: expected {} or {'runs': [...]} (vvloc.provenance), got "
                f"{self.training_record!r:.80}"
            )
        not_f32 = sorted(
            {str(v.dtype) for v in self.state_dict().values() if v.is_floating_point()}
            - {"torch.float32"}
        )
        if not_f32:
            raise TypeError(
                f"the model holds {not_f32} tensors: save a float32 model (model.float()); "
                "load gives float32, and the weights fingerprint would differ"
            )
        bad = _non_finite(self.state_dict())
        if bad:
            raise ValueError(
                f"the model holds non-finite weights ({bad}): a diverged training? Not saved"
            )
        out = Path(directory)
        weights = self.weights_hash()
        meta = {
            "format": CHECKPOINT_FORMAT,
            "version": CONFIG_VERSION,
            "config_hash": self.config_hash(),
            "config": self.config.to_dict(),
            # checked by load: a damaged or swapped weights file is refused, not used
            "weights_hash": weights,
        }
        tensors = {k: v.detach().cpu().contiguous() for k, v in self.state_dict().items()}
        # Everything is serialised before any file is touched (a calibration or record that
        # cannot be written fails here), then written as one change (vvloc._io.write_together),
        # so that new weights never sit beside an old config, calibration or record.
        files = {
            # safetensors' save_file replaces its target with a 0o600 file: write its bytes
            WEIGHTS_FILE: save(tensors),
            CONFIG_FILE: json.dumps(meta, indent=2).encode(),
        }
        if self.calibration:
            files[CALIBRATION_FILE] = calibration_json(self.calibration).encode()
        if isinstance(runs, list) and self.training_record:
            files[TRAINING_FILE] = record_json(weights, runs).encode()
        out.mkdir(parents=True, exist_ok=True)
        write_together(out, files)
        for stale in (CALIBRATION_FILE, TRAINING_FILE):  # would describe other weights
            if stale not in files:
                (out / stale).unlink(missing_ok=True)
        return out

    @classmethod
    def load(
        cls, directory: str | os.PathLike[str], map_location: str | torch.device = "cpu"
    ) -> VVLocNet:
        """Load a checkpoint written by :meth:`save`, in eval mode (dropout off) on
        ``map_location`` (``cpu``, ``cuda[:N]`` or ``auto``: :func:`resolve_device`).

        Raises ``ValueError`` on a malformed or truncated file, a wrong format or version, a
        config that lacks fields or whose hash is not the one recorded (an edited
        ``config.json``: fields such as ``num_angles`` or ``grid_size`` shape no weight, so
        only the hash tells), weights that do not match the architecture (names, shapes and
        dtypes listed: they are never cast), weights whose fingerprint is not the one
        ``config.json`` records (a damaged file; checkpoints saved before 2026-12-05 record
        none), or a calibration whose fields the localizer reads are malformed. A
        ``training.json`` that is malformed or describes other weights is ignored with a
        ``UserWarning`` (it is informational; the weights load)."""
        device = resolve_device(map_location, argument="map_location")
        src = Path(directory)
        check_checkpoint_files(src, "directory")
        cfg_path, w_path = src / CONFIG_FILE, src / WEIGHTS_FILE
        meta = _json_object(cfg_path)
        if meta.get("format") != CHECKPOINT_FORMAT:
            raise ValueError(
                f"{cfg_path}: format {meta.get('format')!r} is not {CHECKPOINT_FORMAT}"
            )
        version = meta.get("version")
        if type(version) is not int or version != CONFIG_VERSION:  # not True, 1.0 or "1"
            raise ValueError(
                f"{cfg_path}: checkpoint version {version!r} is not supported "
                f"(expected {CONFIG_VERSION!r})"
            )
        config = meta.get("config")
        if not isinstance(config, dict):
            raise ValueError(f"{cfg_path}: expected a 'config' object, got {config!r:.80}")
        lacking = sorted({f.name for f in dataclasses.fields(ModelConfig)} - set(config))
        if lacking:
            raise ValueError(f"{cfg_path}: the config lacks the fields {lacking}")
        try:
            cfg = ModelConfig.from_dict(config)
        except (TypeError, ValueError) as e:  # e.g. a field of a newer vvloc
            raise ValueError(f"{cfg_path}: {e}") from None
        stored = meta.get("config_hash")
        if stored != cfg.config_hash() and stored == _hash_as_written(config):
            # saved before configs were normalised (an int in a float field, such as a YAML
            # override sigma_a: 15): the same config, whose hash now reads 15.0
            warnings.warn(
                f"{cfg_path}: config_hash {stored} is the hash of the config as written before "
                f"vvloc normalised config numbers; it is now {cfg.config_hash()}. Maps built "
                "with this checkpoint record the old one: rebuild them (and save the "
                "checkpoint again to update its config.json)",
                UserWarning,
                stacklevel=2,
            )
        elif stored != cfg.config_hash():
            raise ValueError(
                f"{cfg_path}: config_hash {meta.get('config_hash')!r} is not the config's "
                f"({cfg.config_hash()}): the file was edited after the weights were saved"
            )
        # builds a randomly initialised model (overwritten below), drawing from torch's global
        # random stream as a fresh model does: trainers that load an init_checkpoint and then
        # draw from that stream (make model's steps 2-5) depend on it, so it stays so
        model = cls(cfg)
        try:
            # from the file's bytes: safetensors' load_file maps the file and keeps about 8 KB
            # per call (safetensors 0.8), which a service that opens localizers grows by
            state = {k: v.to(device) for k, v in load_safetensors(w_path.read_bytes()).items()}
        except SafetensorError as e:
            raise ValueError(f"{w_path}: not a readable safetensors file ({e})") from None
        expected = model.state_dict()
        missing = sorted(set(expected) - set(state))
        unexpected = sorted(set(state) - set(expected))
        wrong = [
            f"{k}: checkpoint {tuple(state[k].shape)} vs model {tuple(v.shape)}"
            for k, v in expected.items()
            if k in state and state[k].shape != v.shape
        ] + [  # load_state_dict would cast them silently (int32 weights truncated)
            f"{k}: checkpoint {state[k].dtype} vs model {v.dtype}"
            for k, v in expected.items()
            if k in state and state[k].dtype != v.dtype
        ]
        if missing or unexpected or wrong:
            raise ValueError(
                f"{w_path}: weights do not match the architecture of {cfg_path}: "
                f"missing {missing[:5]}{'…' if len(missing) > 5 else ''}, "
                f"unexpected {unexpected[:5]}{'…' if len(unexpected) > 5 else ''}, "
                f"shape or dtype mismatches {wrong[:5]}"
            )
        bad = _non_finite(state)
        if bad:  # never stands in for trained weights, with or without a recorded fingerprint
            raise ValueError(f"{w_path}: holds non-finite weights ({bad})")
        model.load_state_dict(state)
        mine = model.weights_hash()
        recorded = meta.get("weights_hash", _ABSENT)  # none before 2026-12-05
        if recorded is not _ABSENT and recorded != mine:
            raise ValueError(
                f"{w_path}: its weights' fingerprint {mine[:16]} is not the one "
                f"{cfg_path} records ({str(recorded)[:16]}): a damaged weights file, or one "
                "from another checkpoint"
            )
        cal_path = src / CALIBRATION_FILE
        if cal_path.is_file():
            model.calibration = calibration_from_json(
                _check_calibration(_json_object(cal_path), cal_path)
            )
        train_path = src / TRAINING_FILE
        if train_path.is_file():  # informational: a bad record never blocks good weights
            try:
                record = read_record(train_path)
                theirs = record["weights_hash"]
                if theirs != mine:
                    raise ValueError(
                        f"{train_path}: describes other weights (weights_hash {theirs[:16]}, "
                        f"the checkpoint's {mine[:16]})"
                    )
                model.training_record = {"runs": record["runs"]}
            except ValueError as e:
                warnings.warn(f"{e}; the training record is ignored", UserWarning, stacklevel=2)
        return model.to(device).eval()


#: ``config.json`` without a ``weights_hash`` (saved before 2026-12-05), unlike one whose value
#: is ``null``, which is a damaged file.
_ABSENT = object()


def _non_finite(state: dict[str, Tensor]) -> str:
    """The first few floating tensors of ``state`` holding NaN or inf, with how many values
    each ("" when none)."""
    bad = [
        f"{k}: {int((~torch.isfinite(v)).sum())} of {v.numel()}"
        for k, v in state.items()
        if v.is_floating_point() and not bool(torch.isfinite(v).all())
    ]
    return "; ".join(bad[:3]) + (f"; and {len(bad) - 3} more tensors" if len(bad) > 3 else "")
