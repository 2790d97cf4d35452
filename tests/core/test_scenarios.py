"""Motion scenarios: still truth, Lötters' postures, six faces, daily living, consistency."""
import numpy as np
import pytest

from gravcal.core.scenarios import (
    DAILY_POSTURES, MOVING, SAGITTAL_POSTURES, SCENARIOS, SIX_FACES, STILL, TURN, WALK, make_motion, plan_motion,
)


def still_runs(still):
    """(start, end) index pairs of consecutive True runs."""
    d = np.diff(np.concatenate([[0], still.astype(np.int8), [0]]))
    return np.flatnonzero(d == 1), np.flatnonzero(d == -1)


@pytest.mark.parametrize("name", SCENARIOS)
def test_still_periods_are_one_g_and_quiet(name):
    m = make_motion(name, duration=900, fs=100, rng=1)
    assert m.specific_force.shape == (len(m), 3) and m.omega.shape == (len(m), 3)
    assert np.all(np.isfinite(m.specific_force)) and np.all(np.isfinite(m.omega))
    norm = np.linalg.norm(m.specific_force, axis=1)
    assert m.still.any()
    assert np.abs(norm[m.still] - 1).max() < 5e-3
    for a, b in zip(*still_runs(m.still)):
        assert np.linalg.norm(m.specific_force[a:b].std(axis=0)) < 0.02  # sway stays below ~1°
        assert np.abs(m.omega[a:b]).max() < np.deg2rad(5.0)
    if name != "static":
        assert (~m.still).any() and norm[~m.still].max() > 1.02  # the movements move


@pytest.mark.parametrize("orientation", [1, 2])
@pytest.mark.parametrize("theta", [30.0, 105.0])
def test_loetters_postures_stay_within_theta_and_fill_the_cap(orientation, theta):
    m = make_motion("loetters", duration=1800, fs=50, rng=2, orientation=orientation, theta_max_deg=theta)
    up_standing = np.array([0, 0, 1.0]) if orientation == 1 else np.ones(3) / np.sqrt(3)
    f = m.specific_force[m.still]
    ang = np.degrees(np.arccos(np.clip(f @ up_standing / np.linalg.norm(f, axis=1), -1, 1)))
    assert ang.max() <= theta + 1.0  # sway amplitude <= 0.5°
    assert ang.max() > 0.8 * theta  # postures do reach the edge of the cap
    standing = m.posture == 0
    assert standing.any() and np.all(ang[standing[m.still]] < 1.0)
    # symmetric spread (Fig. 6): the mean posture direction stays near standing
    means = np.array([m.specific_force[a:b].mean(axis=0) for a, b in zip(*still_runs(m.still))])
    mean_dir = means.mean(axis=0) / np.linalg.norm(means.mean(axis=0))
    assert np.degrees(np.arccos(mean_dir @ up_standing)) < theta / 2


def test_six_position_covers_all_six_faces():
    m = make_motion("six_position", duration=240, fs=100, rng=3)
    assert m.posture_names == SIX_FACES
    assert set(np.unique(m.posture[m.still])) == set(range(6))
    for face in range(6):
        up = np.zeros(3)
        up[face // 2] = 1.0 if face % 2 == 0 else -1.0
        f = m.specific_force[m.still & (m.posture == face)].mean(axis=0)
        assert np.degrees(np.arccos(f @ up / np.linalg.norm(f))) < 5.0
    assert np.all(m.posture[~m.still] == MOVING)


def test_daily_living_has_gait_lying_and_varied_still_periods():
    m = make_motion("daily_living", duration=3600, fs=100, rng=4)
    assert m.posture_names == DAILY_POSTURES
    walk = m.posture == DAILY_POSTURES.index("walk")
    assert walk.mean() > 0.02
    vert = m.specific_force[walk] @ np.array([0, 0, 1.0])  # waist, board ~ body axes
    assert 0.3 < (np.percentile(vert, 99) - np.percentile(vert, 1)) / 2 < 1.2  # 0.3-1 g gait amplitude
    spec = np.abs(np.fft.rfft(np.linalg.norm(m.specific_force[walk][:2048], axis=1) - 1))
    peak_hz = np.argmax(spec[1:]) * 100 / 2048 + 100 / 2048
    assert 1.2 < peak_hz < 2.5
    lying = np.isin(m.posture, [DAILY_POSTURES.index(p) for p in ("lie_back", "lie_left", "lie_right", "lie_front")])
    assert lying.any()
    tilt = np.degrees(np.arccos(np.clip(m.specific_force[lying & m.still, 2], -1, 1)))
    assert np.median(tilt) > 60  # lying: gravity far from the standing axis (Lötters: theta > 105° needed)
    starts, ends = still_runs(m.still)
    lengths = (ends - starts) / 100.0
    assert lengths.min() < 10 and lengths.max() > 60
    assert 22 <= m.temp[0] <= 26.5  # starts near room temperature
    assert m.temp[-1] > 29.5  # warmed towards skin temperature within the hour
    assert np.all((m.vsupply >= 3.0) & (m.vsupply <= 3.3))


def test_wrist_placement_varies_orientation_more_than_waist():
    spreads = {}
    for placement in ("waist", "wrist"):
        m = make_motion("daily_living", duration=1800, fs=50, rng=5, placement=placement, bed_episode=False)
        f = m.specific_force[m.still]
        spreads[placement] = np.linalg.norm(f.std(axis=0))
    assert spreads["wrist"] > spreads["waist"]


@pytest.mark.parametrize("name", ["loetters", "daily_living", "six_position", "sagittal_postures"])
def test_omega_is_the_rate_of_the_orientation(name):
    """With linear acceleration removed, f = R^T e_up obeys df/dt = -omega x f exactly; central
    differences at 200 Hz are accurate to ~|omega|^2 |f| dt^2 / 6 << 1e-3."""
    plan = plan_motion(name, duration=300, fs=200, rng=6)
    plan.lin[:] = 0.0
    m = plan.render()
    df = np.gradient(m.specific_force, 1 / 200, axis=0)[1:-1]
    pred = -np.cross(m.omega, m.specific_force)[1:-1]
    assert np.abs(pred).max() > 0.2  # real rotations happen (> 11 °/s)
    assert np.abs(df - pred).max() < 1e-3


def test_render_of_any_range_equals_the_one_shot_render():
    plan = plan_motion("daily_living", duration=600, fs=100, rng=7)
    full = plan.render()
    for a, b in [(0, 1), (13, 4099), (30000, 60000), (59999, 60000)]:
        part = plan.render(a, b)
        assert np.array_equal(part.specific_force, full.specific_force[a:b])
        assert np.array_equal(part.omega, full.omega[a:b])
        assert np.array_equal(part.temp, full.temp[a:b])
        assert np.array_equal(part.posture, full.posture[a:b])


def test_same_rng_same_motion_and_static_pose():
    a = make_motion("loetters", duration=60, rng=8)
    b = make_motion("loetters", duration=60, rng=8)
    c = make_motion("loetters", duration=60, rng=9)
    assert np.array_equal(a.specific_force, b.specific_force)
    assert not np.array_equal(a.specific_force, c.specific_force)
    s = make_motion("static", duration=10, rng=1, rotvec=[np.pi / 2, 0, 0])
    np.testing.assert_allclose(s.specific_force, np.tile([0, 1.0, 0], (len(s), 1)), atol=1e-12)
    assert s.still.all()


def test_walk_segments_start_and_end_at_rest():
    plan = plan_motion("daily_living", duration=1800, fs=100, rng=10)
    m = plan.render()
    for i in np.flatnonzero(plan.kind == WALK):
        a = plan.start[i]
        assert np.abs(m.omega[a]).max() < 1e-9


def test_bad_scenario_requests_raise_clear_errors():
    with pytest.raises(ValueError, match="unknown scenario 'jogging'"):
        make_motion("jogging")
    with pytest.raises(ValueError, match="no option"):
        make_motion("loetters", theta=30)
    with pytest.raises(ValueError, match="orientation must be 1"):
        make_motion("loetters", orientation=3)
    with pytest.raises(ValueError, match="theta_max_deg"):
        make_motion("loetters", theta_max_deg=200)
    with pytest.raises(ValueError, match="duration"):
        make_motion("static", duration=-1)
    with pytest.raises(ValueError, match="placement"):
        make_motion("daily_living", placement="ankle")
    with pytest.raises(ValueError, match="mount_pitch_deg"):
        make_motion("sagittal_postures", mount_pitch_deg=90)
    with pytest.raises(ValueError, match="p_lie"):
        make_motion("sagittal_postures", p_lie=1.5)


ENC03J_RANGE = np.deg2rad(300.0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_sagittal_postures_pitch_about_board_y_between_still_postures(seed):
    """The gyro scenario: the board's y axis (the ENC-03J's) stays medio-lateral, many posture
    changes turn about it alone, all rates inside the gyro's ±300 °/s, and the postures give the
    accelerometer gravity along ±x, ±y and beyond 105° from standing (Lötters' condition)."""
    plan = plan_motion("sagittal_postures", duration=900, fs=100, rng=seed)
    m = plan.render()
    assert m.posture_names == SAGITTAL_POSTURES
    assert np.linalg.norm(m.omega, axis=1).max() < 0.7 * ENC03J_RANGE  # peak ~180 °/s
    visited = {SAGITTAL_POSTURES[i] for i in np.unique(m.posture[m.still])}
    assert {"stand", "sit", "bend", "lie_back"} <= visited and visited & {"lie_left", "lie_right"}
    # each transition between two still segments: the rotation integrated from omega, its axis
    about_y = other = 0
    still_idx = np.flatnonzero(plan.kind == STILL)
    for a, b in zip(still_idx[:-1], still_idx[1:]):
        if not np.all(plan.kind[a + 1:b] == TURN) or b == a + 1:
            continue
        i0, i1 = plan.start[a + 1], plan.start[b]
        angle = m.omega[i0:i1].sum(axis=0) / 100.0  # single-axis segments: exact sum of angles
        if np.linalg.norm(angle) < np.deg2rad(10):
            continue
        if abs(angle[1]) / np.linalg.norm(angle) > np.cos(np.deg2rad(3)):
            about_y += 1
            f0 = m.specific_force[plan.start[a]:i0].mean(axis=0)
            f1 = m.specific_force[i1:plan.start[b] + 100].mean(axis=0)
            assert abs(f1[1] - f0[1]) < 0.05  # gravity's y component kept (sway, sideways lean)
        else:
            other += 1
    assert about_y >= 20 and other >= 2, (about_y, other)  # mostly about y; rolls and turns too
    f = m.specific_force[m.still]
    f = f / np.linalg.norm(f, axis=1, keepdims=True)
    up_standing = f[m.posture[m.still] == SAGITTAL_POSTURES.index("stand")].mean(axis=0)
    up_standing /= np.linalg.norm(up_standing)
    assert np.degrees(np.arccos(np.clip(f @ up_standing, -1, 1))).max() > 105.0
    assert f[:, 0].max() > 0.9 and f[:, 0].min() < -0.9  # lying on the back, bending to the floor
    assert max(f[:, 1].max(), -f[:, 1].min()) > 0.9  # lying on a side
