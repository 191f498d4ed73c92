"""Photometric training augmentation: shapes, determinism, what it changes and what it refuses."""

from __future__ import annotations

import numpy as np
import pytest

from vvloc.data.augment import PhotometricAugment


def _images(seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (4, 3, 24, 32), dtype=np.uint8)


def test_same_generator_state_gives_the_same_images_and_input_is_untouched():
    im = _images()
    before = im.copy()
    aug = PhotometricAugment(prob=1.0)
    a = aug(im, np.random.default_rng(7))
    b = aug(im, np.random.default_rng(7))
    assert a.dtype == np.uint8 and a.shape == im.shape
    assert np.array_equal(a, b)
    assert np.array_equal(im, before)
    assert not np.array_equal(a, im)


def test_all_zero_strengths_is_the_identity():
    im = _images(1)
    aug = PhotometricAugment(
        prob=1.0, brightness=0, contrast=0, gamma=0, tint=0, haze=0, camera_jitter=0, noise=0
    )
    assert np.array_equal(aug(im, np.random.default_rng(0)), im)


def test_prob_zero_returns_an_equal_copy():
    im = _images(2)
    out = PhotometricAugment(prob=0.0)(im, np.random.default_rng(0))
    assert np.array_equal(out, im) and out is not im


def test_brightness_only_scales_a_grey_frame_by_one_gain():
    im = np.full((2, 3, 8, 8), 100, np.uint8)
    aug = PhotometricAugment(
        prob=1.0, brightness=0.5, contrast=0, gamma=0, tint=0, haze=0, camera_jitter=0, noise=0
    )
    out = aug(im, np.random.default_rng(3)).astype(int)
    assert len(np.unique(out)) == 1  # one gain for every camera and pixel
    assert round(100 * np.exp(-0.5)) <= out[0, 0, 0, 0] <= round(100 * np.exp(0.5))


def test_full_haze_pulls_the_top_rows_to_the_airlight_more_than_the_bottom_rows():
    im = np.zeros((1, 3, 10, 4), np.uint8)
    aug = PhotometricAugment(
        prob=1.0,
        brightness=0,
        contrast=0,
        gamma=0,
        tint=0,
        haze=1.0,
        haze_prob=1.0,
        camera_jitter=0,
        noise=0,
    )
    # Draw until the haze weight is large, then check the vertical ramp.
    out = max((aug(im, np.random.default_rng(s)) for s in range(20)), key=lambda o: int(o.sum()))
    rows = out[0, 0, :, 0].astype(int)
    assert np.all(np.diff(rows) <= 0) and rows[0] > rows[-1] > 0


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"brightness": -0.1}, "brightness"),
        ({"prob": 1.5}, "prob"),
        ({"noise": float("nan")}, "noise"),
        ({"haze": "strong"}, "haze"),
        ({"gamma": True}, "gamma"),
        ({"brightness": 800.0}, r"augment\.brightness: expected a log range"),  # exp overflows
        ({"noise": 300.0}, r"augment\.noise: expected grey levels"),
    ],
)
def test_bad_parameters_are_refused_by_name(kwargs, match):
    with pytest.raises(ValueError, match=match):
        PhotometricAugment(**kwargs)


def test_from_dict_rejects_unknown_keys_and_accepts_empty():
    assert PhotometricAugment.from_dict({}) == PhotometricAugment()
    with pytest.raises(ValueError, match="unknown keys"):
        PhotometricAugment.from_dict({"hue": 0.1})
    with pytest.raises(ValueError, match=r"augment\.brightness"):
        PhotometricAugment.from_dict({"brightness": "bright"})


@pytest.mark.parametrize(
    ("bad", "err", "match"),
    [
        (np.zeros((3, 8, 8), np.uint8), ValueError, r"got shape \(3, 8, 8\)"),
        (np.zeros((1, 3, 8, 8), np.float32), TypeError, "got dtype float32"),
        ([[1]], TypeError, "got list"),
    ],
)
def test_bad_images_are_refused(bad, err, match):
    with pytest.raises(err, match=rf"^images: expected a uint8 .*{match}"):
        PhotometricAugment()(bad, np.random.default_rng(0))


def test_the_rng_must_be_a_generator():
    with pytest.raises(TypeError, match="rng: expected a numpy Generator, got int"):
        PhotometricAugment()(np.zeros((1, 3, 8, 8), np.uint8), 0)  # type: ignore[arg-type]


def test_numpy_scalars_are_numbers_and_kept_as_floats():
    aug = PhotometricAugment(prob=np.float32(0.5), noise=np.int64(3))
    assert (aug.prob, aug.noise) == (0.5, 3.0) and type(aug.prob) is float
    with pytest.raises(ValueError, match=r"augment\.prob: expected a finite number"):
        PhotometricAugment(prob=np.bool_(True))


def test_an_augment_section_that_is_no_mapping_is_said_to_be_one():
    from vvloc.data.augment import PhotometricAugment

    for raw in ([("prob", 1)], "prob"):
        with pytest.raises(TypeError, match=r"^augment: expected a mapping of fields"):
            PhotometricAugment.from_dict(raw)  # type: ignore[arg-type]
    assert PhotometricAugment.from_dict(None) == PhotometricAugment.from_dict({})
