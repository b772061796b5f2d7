"""Scan patterns: field of view, rates, purity in k, non-repetitive coverage, presets."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from indoorbev_sim import patterns


def az_el_deg(dirs):
    d = np.asarray(dirs, np.float64)
    return np.degrees(np.arctan2(d[:, 1], d[:, 0])), np.degrees(np.arcsin(np.clip(d[:, 2], -1, 1)))


MID = patterns.Mid360Pattern()
_mid_frame = jax.jit(MID.frame)


def test_mid360_spec_fov_rate_and_times():
    f = _mid_frame(7)
    assert f.directions.shape == (20_000, 3) and MID.num_rays == 20_000  # 200k pts/s at 10 Hz
    np.testing.assert_allclose(np.linalg.norm(np.asarray(f.directions), axis=1), 1.0, atol=1e-5)
    az, el = az_el_deg(f.directions)
    assert el.min() >= -7.0 - 1e-3 and el.max() <= 52.0 + 1e-3
    assert el.min() < -6.5 and el.max() > 51.5  # the whole vertical FOV is used
    hist, _ = np.histogram(az, bins=36, range=(-180, 180))
    assert hist.min() > 0.8 * hist.mean()  # 360 deg horizontal, evenly
    # One turn a frame with every ray at its own azimuth (the emitters interleaved): no gap
    # between sorted azimuths over twice the mean 360 / R. A mutation audit: the emitters a
    # whole slot apart (four rays at each azimuth, gaps of 4 x 360 / R) passed.
    ring = np.sort(np.mod(np.asarray(az, np.float64), 360.0))
    gaps = np.diff(np.r_[ring, ring[0] + 360.0])
    assert gaps.max() <= 2 * 360.0 / MID.num_rays
    t = np.asarray(f.time_offsets)
    assert t.min() == 0.0 and t.max() < 0.1 and np.all(np.diff(t) >= 0)  # within one 10 Hz frame
    np.testing.assert_allclose(float(f.start_time), 0.7, rtol=1e-6)


def test_frames_are_pure_functions_of_k():
    a, b = _mid_frame(12345), _mid_frame(jnp.int32(12345))
    np.testing.assert_array_equal(np.asarray(a.directions), np.asarray(b.directions))
    # Eager and jitted evaluation agree up to float32 rounding of fused ops.
    np.testing.assert_allclose(
        np.asarray(MID.frame(12345).directions), np.asarray(a.directions), atol=1e-6
    )
    assert not np.allclose(np.asarray(_mid_frame(12346).directions), np.asarray(a.directions))
    # A negative Python k wraps as a traced int32 one does (it raised an OverflowError).
    wrapped = np.asarray(MID.frame(-1).directions)
    np.testing.assert_array_equal(wrapped, np.asarray(MID.frame(2**32 - 1).directions))
    np.testing.assert_allclose(wrapped, np.asarray(_mid_frame(jnp.int32(-1)).directions), atol=1e-6)


def coverage(frames, n_az=180, n_el=40):
    """Fraction of (azimuth, sin elevation) cells of the FOV hit by the union of frames."""
    hit = np.zeros((n_az, n_el), bool)
    s_lo, s_hi = np.sin(np.radians(-7.0)), np.sin(np.radians(52.0))
    for f in frames:
        az, el = az_el_deg(f.directions)
        i = np.clip(((az + 180) / 360 * n_az).astype(int), 0, n_az - 1)
        j = np.clip(
            ((np.sin(np.radians(el)) - s_lo) / (s_hi - s_lo) * n_el).astype(int), 0, n_el - 1
        )
        hit[i, j] = True
    return hit.mean()


def test_mid360_coverage_keeps_filling_over_frames():
    """Non-repetitive: more frames cover strictly more of the field of view, towards all of it.

    A fine 720 x 160 cell grid (more cells than one frame's rays) is used so one frame cannot
    cover it; a repetitive pattern would stay at the single-frame value.
    """
    frames = [_mid_frame(k) for k in range(10)]
    c1 = coverage(frames[:1], 720, 160)
    c3 = coverage(frames[:3], 720, 160)
    c10 = coverage(frames, 720, 160)
    assert c1 < 0.2 and c1 < c3 < c10
    assert c10 > 0.75


def test_spinning_presets():
    vlp = patterns.SpinningPattern.vlp16()
    f = vlp.frame(3)
    assert f.directions.shape == (1800 * 16, 3)
    _, el = az_el_deg(f.directions)
    np.testing.assert_allclose(np.unique(np.round(el, 4)), np.arange(-15, 16, 2), atol=1e-3)
    t = np.asarray(f.time_offsets)
    assert t.max() < 0.1 and np.all(np.diff(t) >= 0)
    os128 = patterns.SpinningPattern.os128()
    _, el = az_el_deg(os128.frame(0).directions)
    assert os128.num_rays == 128 * 1024 and len(np.unique(np.round(el, 3))) == 128
    assert abs(el.min() + 22.5) < 1e-3 and abs(el.max() - 22.5) < 1e-3
    # Column c points at azimuth 360 c / columns (column-major: beams of a column together),
    # so no column repeats the first one's azimuth at the seam.
    az, _ = az_el_deg(f.directions)
    want = np.repeat(np.arange(1800) * 360.0 / 1800, 16)
    np.testing.assert_allclose(np.mod(az - want + 180.0, 360.0) - 180.0, 0.0, atol=1e-3)
    assert len(np.unique(np.round(np.asarray(f.directions), 5), axis=0)) == 1800 * 16
    # A spinner repeats: frame k only moves its start time.
    np.testing.assert_array_equal(np.asarray(vlp.frame(0).directions), np.asarray(f.directions))
    np.testing.assert_allclose(float(f.start_time), 0.3, rtol=1e-6)


def test_grid_pattern_matches_numpy():
    g = patterns.GridPattern(8, 3, -90, 90, -10, 10)
    az, el = az_el_deg(g.frame(0).directions)
    np.testing.assert_allclose(az.reshape(8, 3)[:, 0], np.linspace(-90, 90, 8), atol=1e-4)
    np.testing.assert_allclose(el.reshape(8, 3)[0], [-10, 0, 10], atol=1e-4)
    full = patterns.GridPattern(360, 2)
    az, _ = az_el_deg(full.frame(0).directions)
    assert len(np.unique(np.round(az, 3))) == 360  # no duplicated seam column


def test_bad_patterns_raise_naming_the_field():
    with pytest.raises(ValueError, match="points_per_second"):
        patterns.Mid360Pattern(points_per_second=200_001)
    # A fractional rate whose frames would have a fractional ray count (10.3 Hz: 19417.5)
    # is refused; one with whole rays per emitter is taken, and its frames have them.
    with pytest.raises(ValueError, match="rays a frame"):
        patterns.Mid360Pattern(frame_rate=10.3)
    for rate, pps in ((12.5, 200_000), (7.5, 150_000)):
        pattern = patterns.Mid360Pattern(points_per_second=pps, frame_rate=rate)
        assert pattern.frame(3).directions.shape == (pps / rate, 3) == (pattern.num_rays, 3)
    with pytest.raises(ValueError, match="elevations_deg"):
        patterns.SpinningPattern(())
    with pytest.raises(ValueError, match="azimuth_steps"):
        patterns.GridPattern(0, 4)
    # These were a ZeroDivisionError, inf start times, or elevations folding back past 90.
    with pytest.raises(ValueError, match=r"Mid360Pattern.num_emitters must be an int >= 1"):
        patterns.Mid360Pattern(num_emitters=0)
    # 20,000 rays a frame do not split over 3 emitters (frame() failed with a reshape error);
    # over 8 they do.
    with pytest.raises(ValueError, match=r"whole multiple of num_emitters \(3\)"):
        patterns.Mid360Pattern(num_emitters=3)
    assert patterns.Mid360Pattern(num_emitters=8).frame(0).directions.shape == (20_000, 3)
    for make in (patterns.Mid360Pattern, patterns.GridPattern,
                 lambda **kw: patterns.SpinningPattern((0.0,), **kw)):  # fmt: skip
        name = make().__class__.__name__
        for rate in (0.0, -10.0, np.nan, np.inf):
            with pytest.raises(ValueError, match=rf"{name}.frame_rate must be finite and > 0"):
                make(frame_rate=rate)
    with pytest.raises(ValueError, match=r"Mid360Pattern: elevations must lie in \[-90, 90\]"):
        patterns.Mid360Pattern(elevation_max_deg=120.0)
    with pytest.raises(ValueError, match=r"SpinningPattern: elevations .* got \[-95.0\]"):
        patterns.SpinningPattern((0.0, -95.0))
    with pytest.raises(ValueError, match=r"GridPattern: elevations"):
        patterns.GridPattern(4, 4, elevation_min_deg=-91.0)


def test_covers_every_ray_of_a_frame_and_nothing_past_the_limits():
    """``covers``: each pattern's own rays are in its field of view; directions a little
    past the elevation limits (and, for a partial grid, the azimuth span) are not."""
    from indoorbev_sim.patterns import _elevation

    grid_part = patterns.GridPattern(36, 8, azimuth_min_deg=-60.0, azimuth_max_deg=60.0)
    cases = [
        (patterns.Mid360Pattern(points_per_second=40_000), -7.0, 52.0),
        (patterns.SpinningPattern.vlp16(), -15.0, 15.0),
        (patterns.GridPattern(36, 8), -30.0, 30.0),
        (grid_part, -30.0, 30.0),
    ]
    for pattern, lo, hi in cases:
        rays = pattern.frame(3).directions
        assert bool(pattern.covers(rays).all()), pattern
        el = np.asarray(_elevation(rays))
        assert np.rad2deg(el.min()) >= lo - 1e-3 and np.rad2deg(el.max()) <= hi + 1e-3
        for deg in (lo - 0.5, hi + 0.5, -89.0, 89.0):
            off = patterns.spherical_to_unit(jnp.float32(0.0), jnp.deg2rad(jnp.float32(deg)))
            assert not bool(pattern.covers(off)), (pattern, deg)
    behind = patterns.spherical_to_unit(jnp.deg2rad(jnp.float32(120.0)), jnp.float32(0.0))
    assert not bool(grid_part.covers(behind))
    assert bool(patterns.GridPattern(36, 8).covers(behind))


def test_mid360_elevations_are_uniform_in_sin_elevation():
    """Equal solid angle, equal rays: sin(elevation) of one frame's rays fills
    [sin(-7 deg), sin(52 deg)] evenly (uniform in the angle itself crowded the top)."""
    s = np.asarray(_mid_frame(7).directions, np.float64)[:, 2]
    hist, _ = np.histogram(s, bins=20, range=(np.sin(np.radians(-7.0)), np.sin(np.radians(52.0))))
    assert hist.sum() == MID.num_rays
    assert hist.min() > 0.97 * hist.mean() and hist.max() < 1.03 * hist.mean(), hist


def test_mid360_firing_times_span_the_frame_at_the_point_rate():
    """points_per_second counts all emitters: the E emitters fire together every
    E / points_per_second s, so a frame's firings fill its 1 / frame_rate s (they took a
    quarter of it)."""
    other = patterns.Mid360Pattern(points_per_second=40_000, num_emitters=2)
    for pattern, frame in ((MID, _mid_frame(0)), (other, other.frame(0))):
        t = np.asarray(frame.time_offsets, np.float64)
        e, per = pattern.num_emitters, pattern.num_rays // pattern.num_emitters
        step = e / pattern.points_per_second
        times, counts = np.unique(t, return_counts=True)
        np.testing.assert_allclose(times, np.arange(per) * step, rtol=1e-6, atol=1e-9)
        assert (counts == e).all()  # the emitters fire together
        np.testing.assert_allclose(t.max() + step, 1.0 / pattern.frame_rate, rtol=1e-6)


def test_mid360_frames_land_between_the_previous_frames_azimuths():
    """Frame k + 1 is rotated by a golden-ratio fraction of a slot: none of its azimuths
    repeats one of frame k's (without the shift every frame fired the same azimuths)."""
    spacing = 2 * np.pi / MID.num_rays  # mean azimuth spacing of one frame's rays
    for k in (0, 1, 12345):
        prev = np.sort(np.radians(az_el_deg(_mid_frame(k).directions)[0]))
        nxt = np.radians(az_el_deg(_mid_frame(k + 1).directions)[0])
        ring = np.concatenate([prev[-1:] - 2 * np.pi, prev, prev[:1] + 2 * np.pi])
        i = np.searchsorted(ring, nxt)
        gap = np.minimum(nxt - ring[i - 1], ring[i] - nxt) / spacing
        assert gap.min() > 0.3, (k, gap.min())


def test_full_turn_grid_has_no_repeated_seam_column():
    """A full turn excludes its end: 360 columns 1 deg apart, 720 distinct rays for
    GridPattern(360, 2) (with the end included -180 and 180 deg both fired)."""
    d = np.asarray(patterns.GridPattern(360, 2).frame(0).directions, np.float64)
    assert len(np.unique(np.round(d, 5), axis=0)) == 720
    columns = np.unwrap(np.arctan2(d[::2, 1], d[::2, 0]))
    np.testing.assert_allclose(np.degrees(np.diff(columns)), 1.0, atol=1e-4)


def test_make_pattern_fires_sim_num_rays_per_frame():
    """``make_pattern(sim)`` is "the scan pattern named by sim.pattern with sim.num_rays
    rays per frame" (SIMULATOR.md, Rays: MID-360 20,000 = 200k points/s at 10 Hz), its
    firing times within one frame. A MID-360 firing twice the rays passed every test (a
    mutation audit)."""
    from indoorbev_sim import generate

    from indoorbev_jax.config import SimConfig

    for n in (2048, 20000):
        pattern = generate.make_pattern(SimConfig(pattern="mid360", num_rays=n))
        frame = pattern.frame(0)
        assert pattern.num_rays == n and frame.directions.shape == (n, 3)
        assert float(jnp.max(frame.time_offsets)) < 1 / pattern.frame_rate
