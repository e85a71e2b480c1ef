"""Procedural textures and silhouettes: ranges, determinism, geometry."""

import numpy as np
import pytest

from evseg.simulator.scene import SHAPES, TEXTURE_FAMILIES, TextureConfig
from evseg.simulator.textures import make_texture, sample_texture_params, shape_alpha


@pytest.mark.parametrize("family", TEXTURE_FAMILIES)
def test_every_family_is_deterministic_and_in_range(family):
    cfg = TextureConfig(family=(family,))
    imgs = []
    for _ in range(2):
        rng = np.random.default_rng(11)
        imgs.append(make_texture(60, 80, sample_texture_params(cfg, rng), rng))
    (a, alpha), (b, _) = imgs
    np.testing.assert_array_equal(a, b)
    assert a.shape == (60, 80) and a.dtype == np.float32
    assert a.min() >= 0.01 and a.max() <= 1.0
    if family != "uniform":
        assert a.std() > 0.01  # has structure
    assert (alpha is not None) == (family in ("grid", "lines"))


def test_grid_alpha_marks_strands_at_the_configured_spacing():
    cfg = TextureConfig(family=("grid",), scale_px=(20.0, 20.0), thickness_px=(2.0, 2.0), angle_deg=(0.0, 0.0), blur_px=0.0)
    rng = np.random.default_rng(0)
    _, alpha = make_texture(200, 200, sample_texture_params(cfg, rng), rng)
    # two strand families of ~2 px every 20 px cover about 1 - (18/20)^2 = 19 % of the area
    assert alpha.mean() == pytest.approx(0.19, abs=0.04)


def test_step_edge_is_an_exact_area_ramp():
    cfg = TextureConfig(family=("step",), angle_deg=(0.0, 0.0), contrast=(1.0, 1.0), mean=(0.5, 0.5))
    rng = np.random.default_rng(0)
    img, _ = make_texture(5, 8, sample_texture_params(cfg, rng), rng)
    # normal along +x through the centre x = 3.5, a pixel boundary: columns 0-3 dark, 4-7 bright
    np.testing.assert_allclose(img[0], [0.01, 0.01, 0.01, 0.01, 1.0, 1.0, 1.0, 1.0])


@pytest.mark.parametrize("shape", SHAPES)
def test_silhouettes_have_the_requested_extent(shape):
    alpha = shape_alpha(shape, 40.0, 0.5, np.random.default_rng(1))
    cols = np.flatnonzero(alpha.max(0) > 0.5)
    assert alpha.min() >= 0 and alpha.max() <= 1.0 + 1e-6
    assert 20 <= cols[-1] - cols[0] + 1 <= 41  # long side <= 40 px (blobs/polygons may be smaller)
    assert alpha[0].max() == 0 and alpha[:, 0].max() == 0  # transparent margin


def test_disc_area_is_pi_r_squared():
    alpha = shape_alpha("disc", 30.0, 1.0, np.random.default_rng(0))
    # anti-aliased coverage sums to the area up to the 4x super-sampling (~1/4 px on the rim)
    assert alpha.sum() == pytest.approx(np.pi * 15**2, rel=0.02)
