import math

import numpy as np
import pytest

from render_jobs.sun import air_mass, sample_suns, sun_from_angles, sun_lamp, sun_sweep


def test_sampling_is_seeded_and_in_range():
    a = sample_suns(np.random.default_rng(0), 200, min_elevation_deg=10, turbidity_range=(2, 10))
    b = sample_suns(np.random.default_rng(0), 200, min_elevation_deg=10, turbidity_range=(2, 10))
    assert a == b
    assert a != sample_suns(np.random.default_rng(1), 200)
    for s in a:
        assert abs(np.linalg.norm(s.direction) - 1) < 1e-9
        assert s.elevation_deg >= 10 - 1e-9
        assert 2 <= s.turbidity <= 10


def test_sampling_is_uniform_in_solid_angle():
    suns = sample_suns(np.random.default_rng(5), 4000, min_elevation_deg=0)
    z = np.array([s.direction[2] for s in suns])
    # uniform in solid angle over the hemisphere means z uniform in [0, 1]
    assert abs(z.mean() - 0.5) < 0.02
    az = np.array([s.azimuth_deg for s in suns])
    assert np.histogram(az, bins=4, range=(0, 360))[0].min() > 900


@pytest.mark.parametrize(
    "bad",
    [
        {"k": 0},
        {"min_elevation_deg": 95},
        {"turbidity_range": (0.5, 3)},
        {"turbidity_range": (5, 2)},
    ],
)
def test_bad_sampling_arguments(bad):
    with pytest.raises(ValueError):
        sample_suns(np.random.default_rng(0), **bad)


def test_air_mass():
    assert air_mass(90) == pytest.approx(1.0, abs=1e-3)
    assert air_mass(30) == pytest.approx(1 / math.sin(math.radians(30)), rel=0.01)
    assert 30 < air_mass(0) < 45


def test_low_sun_is_dimmer_and_warmer():
    high, low = sun_lamp(sun_from_angles(70, 0, 3)), sun_lamp(sun_from_angles(8, 0, 3))
    assert low[0] < high[0]
    warmth = lambda c: c[0] / c[2]  # noqa: E731
    assert warmth(low[1]) > warmth(high[1]) > 1.0


def test_hazy_sun_is_dimmer():
    clear, hazy = sun_lamp(sun_from_angles(45, 0, 2)), sun_lamp(sun_from_angles(45, 0, 9))
    assert hazy[0] < clear[0]
    assert max(clear[1]) == pytest.approx(1.0)


def test_material_suns_are_their_own_stream():
    from render_jobs.specs import derive_seed
    from render_jobs.sun import suns_for_material

    a = suns_for_material(0, 3)
    assert a == suns_for_material(0, 3) and a != suns_for_material(0, 4)
    assert a != suns_for_material(1, 3)
    # not the draws of the material's own seed (which seeds its generator)
    assert a != sample_suns(np.random.default_rng(derive_seed(0, 3)), 5)


def test_a_sweep_turns_the_sun_once_round_at_its_elevation():
    start = sun_from_angles(35.0, 300.0, 4.0)
    suns = sun_sweep(start, 8)
    assert len(suns) == 8 and np.allclose(suns[0].direction, start.direction)
    assert all(abs(s.elevation_deg - 35.0) < 1e-9 and s.turbidity == 4.0 for s in suns)
    steps = [
        (b.azimuth_deg - a.azimuth_deg) % 360
        for a, b in zip(suns, suns[1:] + suns[:1], strict=True)
    ]
    assert np.allclose(steps, 45.0)
    with pytest.raises(ValueError, match="at least one sun"):
        sun_sweep(start, 0)
