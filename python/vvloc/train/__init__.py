"""The VVLoc trainer: the paper's two-stage recipe in a plain PyTorch loop.

Stage 1 trains the global descriptor (triplet + hinge losses on L2-normalised global
descriptors). Stage 2 trains global and local-view descriptors jointly, adding the circle-style
yaw matching loss and the translation-bias loss on (anchor, positive) pairs whose relative pose
ξ_{a→p} (DESIGN.md §3: the positive's frame expressed in the anchor's frame) is known from the
ground truth. Adam, learning rate 1e-4 decayed ×0.95 per epoch; triplets from
:class:`vvloc.data.TripletSampler` with hard-sample mining (triplets that still violate the
triplet margin are re-drawn until they are satisfied). Every random choice is seeded: on the
CPU a run is deterministic and a resumed run equals an uninterrupted one bit for bit. On CUDA
it is not: the backward passes of ``grid_sample`` (padding, polar sampling, deformable
attention), ``scatter_add`` and gathers accumulate with atomics, so two CUDA runs of one config
differ in the last bits and drift apart over epochs (torch offers no deterministic version of
``grid_sample``'s backward, so ``use_deterministic_algorithms`` cannot be switched on).

Outputs in ``out_dir``: ``checkpoint/`` (safetensors weights + JSON config, written each epoch),
``trainer_state.pt`` (optimizer, scheduler, epoch, step, sampler state, for ``--resume``),
``log.jsonl`` (one JSON object per epoch) and ``train_config.yaml`` (the resolved config).
Every checkpoint it writes holds a ``training.json`` (:mod:`vvloc.provenance`): the hardware,
device and wall time of this run and of the runs that produced its ``init_checkpoint``.

With ``val_sessions``, every joint epoch is scored on those held-out sessions against a map of
``val_database`` (:func:`validation_recall`: Recall@1 at 2 m after re-ranking, then by retrieval
alone) and the best epoch so far is kept in ``best/``: checkpoint selection on data that
neither trains the model nor reports its test figures.

An optional third stage (``head_epochs``) refines the global-descriptor head alone on frozen
encoder features: every training frame is encoded once (eval mode, no augmentation) and its
polar BEV cached; each step then draws anchors and positives from the sampler and, as the
negative, one of the ``head_negatives`` frames nearest the anchor in descriptor space among
those that are not its positives (beyond ``neg_radius`` or on another floor), the
descriptors being refreshed every :data:`HEAD_REFRESH` steps (the sampler's hard pool and
``cross_floor_fraction`` play no part there: mining finds the look-alikes). The BEV, the local-view
descriptors and so the metric localization are unchanged by it; retrieval is what it improves.
It can run after stages 1-2, or alone on a trained model (``init_checkpoint``), also with a
different ``global_head`` than the initial model's (a NetVLAD head then starts from a
spherical k-means of the cached cell features,
:meth:`vvloc.nets.heads.NetVLADHead.init_from_features`).

An optional fourth stage (``local_epochs``), ours, refines the local-view decoder and the
interactor alone on frozen BEVs: every training frame is encoded once (eval mode, no
augmentation) and its BEV cached with its pose; each step draws (anchor, positive) pairs from the
sampler and applies the yaw matching loss, the translation-bias loss and, with
``tbias_near_weight`` > 0, :func:`vvloc.losses.near_translation_loss` to the anchor's BEV
padded at the ground-truth relative pose. The BEV and the global descriptors, and so retrieval
and loop detection by descriptor, are unchanged by it; the re-ranking and the metric pose are
what it changes.

Frames without image content (:func:`vvloc.data.has_image_content`: every camera's picture
flat, e.g. a covered rig or a black stretch) look alike wherever they were taken: no model can
tell them apart, and their triplets would stay violated in the hard pool for good. As the map
builder and the localizer do, training leaves them out: stages 1-2 drop a batch's triplets that
hold one (found as the worker loads them) and the stage-3/4 caches find them as they encode
every frame; either way the sampler excludes the frame from every later draw
(:meth:`vvloc.data.TripletSampler.exclude`, kept in the trainer state for ``--resume``), with a
warning that names them and, in stages 1-2, an epoch log field ``blank_triplets``.
"""

from vvloc.train.config import HEAD_FIELDS, HEAD_REFRESH, RESUMABLE_CHANGES, SELECT_BY, TrainConfig
from vvloc.train.data import TripletFrames
from vvloc.train.run import check_run_folder, run_lock, train
from vvloc.train.steps import StepLosses, global_losses, near_losses, near_seed, training_losses
from vvloc.train.trainer import Trainer, pick_device, seed_everything
from vvloc.train.validation import loop_validation, validation_query_count, validation_recall

__all__ = [
    "HEAD_FIELDS",
    "HEAD_REFRESH",
    "RESUMABLE_CHANGES",
    "SELECT_BY",
    "StepLosses",
    "TrainConfig",
    "Trainer",
    "TripletFrames",
    "check_run_folder",
    "global_losses",
    "loop_validation",
    "near_losses",
    "near_seed",
    "pick_device",
    "run_lock",
    "seed_everything",
    "train",
    "training_losses",
    "validation_query_count",
    "validation_recall",
]
