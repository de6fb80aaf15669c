"""``sterile`` where a role's track was not followed (a gap of its trajectory, or outside its
keyframes): what a safety reviewer relies on is that a touch there is never lost, and never
given to someone we did not follow. The scene is built geometry (``test_sterile.py``'s table
slab, bodies and arms), the roles real trajectories read as ``egosurg sterile`` reads them."""

from __future__ import annotations

import numpy as np

from protocol.formats.trajectory import Keyframe, Trajectory
from reconstructor.replay.path import CameraPath
from reconstructor.replay.sterile import NOT_FOLLOWED, Region, SterileConfig, judge_field
from reconstructor.replay.sterile_run import _eyes
from tests.reconstructor.test_sterile import BOX, _arm, _body, _slab

TIMES_S = [0.5 * k for k in range(12)]  # 0.0 .. 5.5 s
GAP_S = (2.0, 4.0)  # nobody followed the radiographer from 2.0 to 4.0 s
TOUCH_S = 3.0  # inside the gap
NEAR = np.array([0.0, -0.95, 1.6])  # where the radiographer stood when last seen
FAR = np.array([0.0, 0.95, 1.6])  # across the table


def _role(name: str, eye: np.ndarray, times_s, gaps_s=()) -> CameraPath:
    keys = tuple(Keyframe(time_s=t, eye_m=tuple(eye), look_at_m=(0.0, 0.0, 0.8))
                 for t in times_s)  # fmt: skip
    return CameraPath(Trajectory(name=name, keyframes=keys, gaps_s=gaps_s))


def _radiographer(gap: bool = True, name: str = "radiographer") -> CameraPath:
    """Seen standing at ``NEAR`` at every timestamp but those inside the gap."""
    if not gap:
        return _role(name, NEAR, TIMES_S)
    seen = [t for t in TIMES_S if not GAP_S[0] < t < GAP_S[1]]
    return _role(name, NEAR, seen, (GAP_S,))


def _contacts(paths: list[CameraPath], reacher: np.ndarray, config=None, standing=()) -> list:
    """The contact events when a person standing at ``reacher`` reaches into the box at
    ``TOUCH_S``; ``standing``: other people's eyes, standing still throughout."""
    cfg = config or SterileConfig()
    rng = np.random.default_rng(7)
    reg = Region(BOX, cfg)
    frames = []
    for t in TIMES_S:
        parts = [_slab(), *(_body(e, rng) for e in standing)]
        if t == TOUCH_S:
            hand = (reacher[0], 0.3 * np.sign(reacher[1]), 0.97)  # 0.3 m inside the box
            parts += [_body(reacher, rng), _arm(reacher, hand, rng)]
        frames.append(reg.select(np.concatenate(parts)))
    stamps = [(t, f"t{k}") for k, t in enumerate(TIMES_S)]
    eyes = [_eyes(paths, t) for t in TIMES_S]
    _, events = judge_field(reg, frames, [None] * len(frames), stamps, eyes)
    return [(e.role, e.start_s, e.sterile_role) for e in events]


def test_a_touch_inside_a_roles_gap_is_not_given_to_its_stale_eye():
    """The person at the radiographer's last-seen spot reaches in while nobody follows the
    radiographer: we cannot say who it is, so the touch is kept as a person not followed."""
    assert _contacts([_radiographer(gap=False)], NEAR) == [("radiographer", TOUCH_S, False)]
    assert _contacts([_radiographer()], NEAR) == [(NOT_FOLLOWED, TOUCH_S, False)]


def test_a_touch_from_where_no_followed_eye_is_is_kept_not_dropped():
    """Unfollowed, the radiographer walked round the table and reached in from the far side:
    the stale eye is 1.9 m away, too far for that arm, and the touch must still be reported."""
    assert _contacts([_radiographer(gap=False)], FAR) == []  # followed there: nobody's arm
    assert _contacts([_radiographer()], FAR) == [(NOT_FOLLOWED, TOUCH_S, False)]


def test_outside_a_roles_keyframes_it_is_not_followed_either():
    seen_until_2 = _role("radiographer", NEAR, [t for t in TIMES_S if t <= 2.0])
    assert _contacts([seen_until_2], NEAR) == [(NOT_FOLLOWED, TOUCH_S, False)]


def test_a_touch_joined_to_a_followed_body_goes_to_that_role():
    """A followed porter's own arm during the radiographer's gap stays the porter's."""
    porter = _role("porter", FAR, TIMES_S)
    events = _contacts([_radiographer(), porter], FAR, standing=[FAR])
    assert events == [("porter", TOUCH_S, False)]


def test_a_gowned_roles_work_is_allowed_only_while_we_follow_them():
    """The surgeon's hands in the field are not a contact while followed; inside the
    surgeon's gap the same reach is reported, since we cannot say it was the surgeon."""
    cfg = SterileConfig(sterile_roles=("surgeon",))
    assert _contacts([_radiographer(gap=False, name="surgeon")], NEAR, cfg) == [
        ("surgeon", TOUCH_S, True)
    ]
    assert _contacts([_radiographer(name="surgeon")], NEAR, cfg) == [(NOT_FOLLOWED, TOUCH_S, False)]
