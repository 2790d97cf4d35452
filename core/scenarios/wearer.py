"""A wearer's day: daily living (waist or wrist) and the sagittal posture set."""
from __future__ import annotations

import numpy as np

from .motion import _Q, DEG, _supply_profile, _temp_profile
from .planner import _lognormal_s, _mount, _Planner, _ry, _rz, _tilt

DAILY_POSTURES = ("stand", "sit", "lie_back", "lie_left", "lie_right", "lie_front", "walk")
_P = {name: i for i, name in enumerate(DAILY_POSTURES)}


def _body(posture: str, heading: float, rng: np.random.Generator) -> _Q:
    """Body (x forward, y left, z up) -> world for a posture, with natural variation."""
    yaw = _rz(heading)
    if posture in ("stand", "walk"):
        return yaw * _ry(rng.normal(0, 3) * DEG)
    if posture == "sit":
        return yaw * _ry(-rng.uniform(10, 30) * DEG)  # pelvis/trunk leaning back
    roll = {"lie_back": 0.0, "lie_left": np.pi / 2, "lie_right": -np.pi / 2, "lie_front": np.pi}[posture]
    return yaw * _ry(-np.pi / 2) * _rz(roll + rng.normal(0, 8) * DEG) * _tilt(rng, 5)


def _arm(posture: str, rng: np.random.Generator) -> _Q:
    """Forearm (wrist sensor) relative to the body: hanging when standing, resting on the lap
    when sitting, anywhere when lying; varies from one still period to the next."""
    nominal = {"stand": _ry(np.pi / 2), "walk": _ry(np.pi / 2), "sit": _ry(0.3)}.get(posture)
    if nominal is None:
        return _Q.random(rng)
    return nominal * _tilt(rng, 40 if posture == "sit" else 20)


def _plan_daily_living(duration, fs, rng, *, placement="waist", mount_rotvec=None, day_start_h=8.0,
                       bed_episode=None, temp_profile="body"):
    """Stand, sit, walk, lie down (back, sides) with quasi-static periods of varying length.

    Days follow the clock from day_start_h; nights (23:00-07:00) are spent lying with turns.
    Records shorter than 6 h contain one going-to-bed episode (Lötters: needed to calibrate
    all parameters), unless bed_episode=False.
    """
    if placement not in ("waist", "wrist"):
        raise ValueError(f"placement must be 'waist' or 'wrist', got {placement!r}")
    wrist = placement == "wrist"
    mount = _mount(None, mount_rotvec)
    heading = rng.uniform(0, 2 * np.pi)

    def sensor(posture: str) -> _Q:
        body = _body(posture, heading, rng)
        return body * (_arm(posture, rng) if wrist else _Q.identity()) * mount

    p = _Planner(duration, fs, rng, sensor("stand"))
    bed = bool(duration < 6 * 3600) if bed_episode is None else bool(bed_episode)
    bed_at = rng.uniform(0.3, 0.6) * duration if bed else np.inf
    state = "stand"

    def hold(posture: str, total: float, median: float) -> None:
        """Stay in a posture for `total` s as several still periods with small fidgets between."""
        end = p.t_end + total
        while p.t_end < end and not p.full:
            p.still(min(_lognormal_s(rng, median, 2.0, 1800.0), max(end - p.t_end, 0.5)), _P[posture],
                    sway_deg=0.8 if posture in ("stand", "sit") else 0.3)
            if p.t_end < end:
                fidget = p.cur * _tilt(rng, 15 if wrist else 6)
                p.turn(fidget, dur=rng.uniform(0.8, 2.0), bump_g=0.05)

    def lie_down(minutes: tuple[float, float], sides: int) -> None:
        nonlocal state
        p.turn(sensor("sit"), bump_g=0.15)
        p.still(rng.uniform(2, 6), _P["sit"])
        for k in range(sides):
            side = "lie_back" if k == 0 else str(rng.choice(["lie_left", "lie_right", "lie_back", "lie_front"],
                                                            p=[0.35, 0.35, 0.2, 0.1]))
            p.turn(sensor(side), bump_g=0.1)
            hold(side, rng.uniform(*minutes) * 60, median=120.0)
            if p.full:
                return
        p.turn(sensor("sit"), bump_g=0.15)
        p.still(rng.uniform(2, 6), _P["sit"])
        state = "sit"

    while not p.full:
        clock_h = (day_start_h + p.t_end / 3600.0) % 24.0
        if clock_h >= 23.0 or clock_h < 7.0:  # night
            lie_down((10, 60), int(rng.integers(6, 14)))
            continue
        if p.t_end >= bed_at:
            bed_at = np.inf
            lie_down((0.5, 2.0), 3)
            continue
        nxt = {"stand": ["walk", "sit", "stand"], "walk": ["stand", "sit"], "sit": ["stand", "sit"]}[state]
        probs = {"stand": [0.5, 0.3, 0.2], "walk": [0.7, 0.3], "sit": [0.6, 0.4]}[state]
        new = str(rng.choice(nxt, p=probs))
        if new == "walk":
            heading = rng.uniform(0, 2 * np.pi)
            p.turn(sensor("walk"), bump_g=0.1)
            lateral = np.array([-np.sin(heading), np.cos(heading), 0.0])
            step = rng.uniform(1.6, 2.0)
            if wrist:
                p.walk(rng.uniform(10, 120), _P["walk"], heading, lateral, rng.uniform(15, 30), step,
                       rng.uniform(0.4, 0.8), rng.uniform(0.4, 0.8), 0.15, stride=True)
            else:
                p.walk(rng.uniform(10, 120), _P["walk"], heading, lateral, rng.uniform(2, 5), step,
                       rng.uniform(0.3, 0.6), rng.uniform(0.15, 0.3), 0.1)
        else:
            p.turn(sensor(new), bump_g=0.15 if new != state else 0.05)
            hold(new, _lognormal_s(rng, 60.0 if new == "stand" else 300.0, 3.0, 3600.0),
                 median=8.0 if new == "stand" else 40.0)
        state = new
    return p.plan("daily_living", DAILY_POSTURES, _temp_profile(temp_profile, rng), _supply_profile(rng))


SAGITTAL_POSTURES = ("stand", "sit", "bend", "kneel", "prostrate", "lie_back", "lie_left", "lie_right", "lie_front",
                     "walk")
_S = {name: i for i, name in enumerate(SAGITTAL_POSTURES)}


def _rx(a: float) -> _Q:
    return _Q.from_rotvec([a, 0.0, 0.0])


def _plan_sagittal_postures(duration, fs, rng, *, mount_pitch_deg=None, lateral_deg=0.5, p_lie=0.35,
                            still_s=(3.0, 15.0), temp_profile="body"):
    """Posture transitions with the board's y axis medio-lateral (a trunk- or waist-worn logger):
    sit-to-stand, bending to pick something up, lying down and getting up, short walks, turns
    on the spot, as in a mobility/transfer protocol or a morning at home.

    Standing: board x forward, y to the left (medio-lateral: the ENC-03J's sensitive axis),
    z up; the belt clip tilts the board by ``mount_pitch_deg`` about y (drawn within ±15° when
    None). The transitions between stand, sit, bend, lie_back (and back up) are pitch rotations
    about board y (sitting up goes through a forward lean, standing up from a chair too), so the
    gyro sees the whole rotation; rolls to the sides and the front while lying turn about the
    body's long axis (board z: not seen by the gyro, but they give the accelerometer gravity
    along ±y); turns on the spot are about the vertical (gravity unchanged); walking pitches
    the trunk about y by a few degrees at the step frequency. Each posture also tilts sideways
    by N(0, ``lateral_deg``) (a small rotation the gyro cannot see). Peak rates stay below
    ~170 °/s (a 80° bend in 0.9 s), inside the ENC-03J's ±300 °/s.

    A lying episode (lie back, maybe roll to a side and the front, roll back, sit up, stand up)
    follows with probability ``p_lie`` after each standing period, and at the latest after four
    episodes without one (the accelerometer needs gravity along ±y for its calibration).
    """
    mount_pitch = rng.uniform(-15.0, 15.0) if mount_pitch_deg is None else float(mount_pitch_deg)
    if not abs(mount_pitch) <= 60.0:
        raise ValueError(f"mount_pitch_deg must be within ±60° (board y stays medio-lateral), got {mount_pitch_deg!r}")
    if not 0.0 <= float(lateral_deg) <= 5.0:
        raise ValueError(f"lateral_deg must be within 0..5° (a sideways lean, not a roll), got {lateral_deg!r}")
    if not 0.0 <= float(p_lie) <= 1.0:
        raise ValueError(f"p_lie must be a probability, got {p_lie!r}")
    mount = _ry(mount_pitch * DEG)
    heading = rng.uniform(-np.pi, np.pi)

    def lateral() -> _Q:
        return _rx(rng.normal(0.0, lateral_deg) * DEG)

    def trunk(pitch_deg: float, roll: float = 0.0) -> _Q:
        """Sensor orientation: heading, then trunk pitch about the medio-lateral axis, then (lying)
        the roll about the body's long axis, then a small sideways tilt, then the clip."""
        return _rz(heading) * _ry(pitch_deg * DEG) * _rz(roll) * lateral() * mount

    p = _Planner(duration, fs, rng, trunk(rng.normal(0, 2)))

    def hold(posture: str, lo: float | None = None, hi: float | None = None) -> None:
        a, b = still_s
        p.still(rng.uniform(a if lo is None else lo, b if hi is None else hi), _S[posture],
                sway_deg=0.3 if posture.startswith("lie") else 0.6)

    def move(target: _Q, dur: float, bump_g: float = 0.1) -> None:
        p.turn(target, dur=dur, bump_g=bump_g)

    def stand_up() -> None:
        move(trunk(rng.uniform(25, 45)), rng.uniform(0.7, 1.1), 0.15)  # lean forward over the feet, then rise
        move(trunk(rng.normal(0, 2)), rng.uniform(0.8, 1.4), 0.2)

    def sit_down() -> None:
        move(trunk(-rng.uniform(5, 25)), rng.uniform(1.0, 2.0), 0.15)  # leaning back against the backrest

    def lie_episode() -> None:
        sit_down()
        hold("sit", 2.0, 6.0)
        move(trunk(-90 + rng.normal(0, 4)), rng.uniform(1.5, 3.0))  # lie back
        hold("lie_back")
        if rng.random() < 0.7:  # roll onto a side (about the body's long axis), maybe on to the front
            side = rng.choice([-1.0, 1.0])
            name = "lie_left" if side > 0 else "lie_right"
            move(trunk(-90 + rng.normal(0, 4), side * (np.pi / 2 + rng.normal(0, 0.08))), rng.uniform(1.2, 2.5))
            hold(name)
            if rng.random() < 0.3:
                move(trunk(-90 + rng.normal(0, 4), side * (np.pi + rng.normal(0, 0.05))), rng.uniform(1.2, 2.5))
                hold("lie_front")
                move(trunk(-90 + rng.normal(0, 4), side * (np.pi / 2 + rng.normal(0, 0.08))), rng.uniform(1.2, 2.5))
                hold(name, 1.0, 4.0)  # back over the same side
            move(trunk(-90 + rng.normal(0, 4)), rng.uniform(1.5, 3.0))  # back onto the back
            hold("lie_back", 2.0, 8.0)
        move(trunk(-rng.uniform(5, 25)), rng.uniform(1.5, 3.0), 0.2)  # sit up
        hold("sit", 2.0, 8.0)
        stand_up()

    def bend(deep: bool) -> None:
        """Pick something up with bent knees, or reach the floor with straight legs (deep: hip and
        lumbar flexion together take the trunk past horizontal)."""
        move(trunk(rng.uniform(95, 120) if deep else rng.uniform(35, 80)), rng.uniform(1.2, 2.0), 0.15)
        hold("bend", 1.5, 6.0)
        move(trunk(rng.normal(0, 2)), rng.uniform(1.2, 2.0), 0.15)

    def kneel() -> None:
        """Kneel, then the forehead to the floor (looking under a bed, prayer, a stretch)."""
        move(trunk(rng.normal(5, 3)), rng.uniform(1.2, 2.0), 0.2)
        hold("kneel", 1.5, 5.0)
        move(trunk(rng.uniform(120, 150)), rng.uniform(1.5, 2.5), 0.1)
        hold("prostrate", 2.0, 8.0)
        move(trunk(rng.normal(5, 3)), rng.uniform(1.5, 2.5), 0.1)
        hold("kneel", 1.5, 5.0)
        stand_up()

    # episodes between standing periods; a lying one and one with the trunk past horizontal at
    # least every fourth episode (the accelerometer's sensitivities need gravity against +z too)
    since_lie = since_floor = 0
    while not p.full:
        hold("stand")
        if p.full:
            break
        since_lie, since_floor = since_lie + 1, since_floor + 1
        if since_lie >= 4 or rng.random() < p_lie:
            since_lie = 0
            lie_episode()
            continue
        what = "floor" if since_floor >= 4 else rng.choice(["sit", "bend", "floor", "walk", "turn"],
                                                            p=[0.25, 0.3, 0.15, 0.15, 0.15])
        if what == "sit":
            sit_down()
            hold("sit")
            stand_up()
        elif what == "bend":
            deep = rng.random() < 0.5
            since_floor = 0 if deep else since_floor
            bend(deep)
        elif what == "floor":
            since_floor = 0
            kneel() if rng.random() < 0.5 else bend(True)
        elif what == "walk":
            lateral_axis = np.array([-np.sin(heading), np.cos(heading), 0.0])
            p.walk(rng.uniform(5, 25), _S["walk"], heading, lateral_axis, rng.uniform(2, 5), rng.uniform(1.6, 2.0),
                   rng.uniform(0.3, 0.6), rng.uniform(0.15, 0.3), 0.1)
        else:  # turn on the spot: about the vertical, gravity unchanged in the board frame
            turn = rng.uniform(45, 180) * rng.choice([-1.0, 1.0]) * DEG
            heading += turn
            move(_rz(turn) * p.cur, 0.8 + 1.5 * abs(turn) / np.pi + rng.uniform(0, 0.5), 0.05)
    return p.plan("sagittal_postures", SAGITTAL_POSTURES, _temp_profile(temp_profile, rng), _supply_profile(rng))
