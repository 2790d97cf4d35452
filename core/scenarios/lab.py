"""Lab scenarios: a board held still, Lötters' tilt protocol, the six-position turns."""
from __future__ import annotations

import numpy as np

from .motion import _Q, DEG, E_UP, _supply_profile, _temp_profile
from .quaternion import align_quat
from .planner import _mount, _Planner, _rz, _tilt


def _plan_static(duration, fs, rng, *, rotvec=None, sway_deg=0.0, temp_profile="room"):
    r0 = _Q.from_rotvec(np.asarray(rotvec, float).reshape(3)) if rotvec is not None else _Q.random(rng)
    p = _Planner(duration, fs, rng, r0)
    p.still(duration, 0, sway_deg=sway_deg, sway_acc_g=0.0)
    return p.plan("static", ("static",), _temp_profile(temp_profile, rng), _supply_profile(rng))


def _plan_loetters(duration, fs, rng, *, orientation=1, theta_max_deg=90.0, p_stand=0.3, still_s=(3.0, 15.0),
                   sway_deg=0.5, mount_rotvec=None, temp_profile="body"):
    """Lötters 1998 sec. 3: postures spread symmetrically up to theta from standing (Fig. 6)."""
    theta_max = float(theta_max_deg)
    if not 0.0 <= theta_max <= 180.0:
        raise ValueError(f"theta_max_deg must be within 0..180°, got {theta_max_deg!r}")
    mount = _mount(orientation, mount_rotvec)
    p = _Planner(duration, fs, rng, mount)
    cos_max = np.cos(theta_max * DEG)
    label = 0
    first = True
    while not p.full:
        if first or rng.random() < p_stand:
            theta, lab = 0.0, 0
        else:  # uniform over the spherical cap of half-angle theta_max
            theta = np.arccos(rng.uniform(cos_max, 1.0))
            label += 1
            lab = label
        az = rng.uniform(0, 2 * np.pi)
        tilt = _Q.from_rotvec(theta * np.array([np.cos(az), np.sin(az), 0.0]))
        target = tilt * _rz(rng.uniform(-np.pi, np.pi)) * mount
        if not first:
            p.turn(target)
        else:
            p.cur = target
        first = False
        # sway tilts a little beyond theta_max; keep it inside so postures respect the cap
        p.still(rng.uniform(*still_s), lab, sway_deg=sway_deg)
    return p.plan("loetters", (), _temp_profile(temp_profile, rng), _supply_profile(rng))


SIX_FACES = ("+x up", "-x up", "+y up", "-y up", "+z up", "-z up")


def _face_rotation(face: int) -> _Q:
    axis = np.zeros(3)
    axis[face // 2] = 1.0 if face % 2 == 0 else -1.0
    if face // 2 == 2:  # the smallest rotation is ill-defined for antiparallel vectors; z faces explicitly
        return _Q.identity() if face == 4 else _Q.from_rotvec([np.pi, 0, 0])
    return _Q(align_quat(E_UP, axis))


def _plan_six_position(duration, fs, rng, *, hold_s=(8.0, 15.0), handling_s=(3.0, 6.0), tilt_deg=3.0,
                       temp_profile="room"):
    """Bragge-style: each face up and down in turn, handled between, repeated to fill the duration."""
    order = (4, 5, 0, 1, 2, 3)
    p = _Planner(duration, fs, rng, _face_rotation(order[0]))
    k = 0
    while not p.full:
        face = order[k % 6]
        target = _rz(rng.uniform(-np.pi, np.pi)) * _tilt(rng, tilt_deg) * _face_rotation(face)
        if k:
            p.turn(target, dur=rng.uniform(*handling_s), bump_g=0.3)
        else:
            p.cur = target
        p.still(rng.uniform(*hold_s), face, sway_deg=0.05, sway_acc_g=0.0005)
        k += 1
    return p.plan("six_position", SIX_FACES, _temp_profile(temp_profile, rng), _supply_profile(rng))
