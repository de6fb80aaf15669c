"""The settings of ``egosurg people``: a frozen dataclass with units in every name and the reason
for each default beside it."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

from reconstructor.errors import ReconstructConfigError


@dataclass(frozen=True, kw_only=True)
class PeopleConfig:
    # the height map's cell: a head is about 0.2 m across, so 4 cm gives it ~20 cells
    cell_m: float = 0.04
    # a point counts only with this many points in the 3 x 3 x 3 cubes of cell_m around it
    # (stereo outliers scatter; a surface is dense; 12 rather than 8 since a case's full-scale
    # evidence is read: EVALUATION.md, change 15)
    min_points_per_cell: int = 12
    # nothing taller or shorter stands in an OR: head tops of adults, ceiling equipment excluded
    head_top_min_m: float = 1.35
    head_top_max_m: float = 2.05
    # a head: the column's top stands this much above the cells 0.2-0.35 m around it ...
    head_drop_m: float = 0.15
    # ... in at least this share of them (a neighbour's shoulder or a boom can fill the rest)
    head_isolation_min: float = 0.6
    # shoulders: the points 0.25-0.45 m below the top within 0.35 m of the head's axis span at
    # least this wide (a person is ~0.45 m across the shoulders) and this deep (a thin drape or
    # a screen is not a torso)
    shoulder_width_min_m: float = 0.28
    shoulder_depth_min_m: float = 0.10
    # background: a cube of space holding points in this share of the timestamps is the room's
    # (learned from the case itself when it has at least background_min_frames timestamps)
    background_share: float = 0.9
    background_min_frames: int = 10
    # a body under the head: points in this share of the 10 cm slices from the knees to the neck
    min_column_share: float = 0.7
    # ... or, as a doubtful head (below match_confidence) that only fills a track's gap between
    # two sightings, in this share of them: legs hidden behind the table or a neighbour fail the
    # check above most; taken as sure heads they start false tracks and swap people
    # (EVALUATION.md, changes 26-26e; 0: none)
    column_fill_share: float = 0.4
    # two heads closer than this are one
    min_head_separation_m: float = 0.3
    # tracking: a detection joins a track within this distance of where the track's velocity
    # (at most max_speed_m_s) puts it, plus gate_growth_m_s per second unseen (staff stand
    # 0.5-1 m apart: a wide gate hands one person's track to a neighbour; 0.4 rather than 0.3
    # and 0.8 m/s rather than 1.5 since tracks coast for 1 s only: EVALUATION.md, changes 17, 19)
    gate_m: float = 0.4
    gate_growth_m_s: float = 0.4
    max_speed_m_s: float = 0.8
    # ... and whose head top is within height_gate_m of the track's usual height (people differ
    # by 5-20 cm; a head stays within a few cm of its height unless the person bends), each
    # metre of difference costing as much as height_weight metres of distance (a head 5 cm off
    # the track's height costs as much as one 30 cm off where it should be: within the gate,
    # height tells neighbours apart better than place; EVALUATION.md, change 23)
    height_gate_m: float = 0.15
    height_weight: float = 6.0
    # a new track is tentative (not reported, and matched only after the confirmed ones) until
    # it is seen at confirm_seen of its first confirm_timestamps timestamps: a neighbour's
    # shoulder or stereo noise makes heads that last one or two
    confirm_seen: int = 3
    confirm_timestamps: int = 5
    # a detection less sure of itself than this is not given to any track: a doubtful head
    # next to a person is more often their neighbour's shoulder or stereo noise than the
    # person, and taking it bends the track's velocity towards the neighbour
    match_confidence: float = 0.5
    # a head left over this close to a confirmed track's is that person again, not a new one
    # (heads are found at least min_head_separation_m apart; two people's, 0.5 m or more),
    # unless it is higher than that track's usual top by more than height_gate_m
    duplicate_m: float = 0.35
    # a track with no detection for longer than this ends (the person left or is lost; a
    # track coasting longer drifts onto a neighbour, and the linking over the whole case below
    # joins the person's tracks across the time unseen: EVALUATION.md, change 16) ...
    max_gap_s: float = 1.0
    # ... and a track starting within this long after, where the gate reaches, continues it
    stitch_gap_s: float = 6.0
    # ... and within this speed of where it was last seen (a walker missed for a few seconds
    # walks on; the height over each track's whole life and the least total cost over the case
    # keep neighbours apart: EVALUATION.md, changes 21 and 22)
    link_speed_m_s: float = 1.5
    # a track that stays within static_radius_m of one place (90 % of its heads) with more than
    # static_share_max of the room's background cubes round its head (the median over its
    # detections) is equipment the background learned in part, not a person (in the sim, over
    # 2 % round 7-21 % of people's heads and round 80-95 % of false heads that stay); a wider
    # radius also takes people who stand still most of a short recording
    static_share_max: float = 0.05
    static_radius_m: float = 0.5
    # ... and a track with more than static_share_moving of them is equipment wherever its heads
    # wander (stereo noise on a boom or a lamp hops about; in the sim the people's tracks have
    # at most 0.16 at the median, the false ones up to 0.36; 0: none is)
    static_share_moving: float = 0.25
    # ... and a track whose head top over its whole life (the median) is within edge_head_m of
    # head_top_min_m or head_top_max_m is not a person: in the sim's nine 60 s runs five false
    # tracks sit at 1.36-1.37 m (one beside a cleaner for 23 s) or 2.02-2.03 m, every other
    # track at 1.44-1.96 m, the people's at 1.87 m or lower (EVALUATION.md, change 25; 0: none is)
    edge_head_m: float = 0.05
    # two tracks whose heads stay within merge_m of each other through all the time they share
    # (where one is missed, the line between its sightings), of one height over their whole
    # lives (within merge_height_m), follow one person and are joined (two people's heads are
    # 0.5 m or more apart: 0.6 joined neighbours walking 0.55 m apart; EVALUATION.md, change
    # 24; 0: never)
    merge_m: float = 0.5
    merge_height_m: float = 0.15
    # a track missed between two timestamps at most fill_span_s apart at which it was seen takes
    # a head no track took there, however doubtful, within fill_m of the line between them and
    # within height_gate_m of their height (most misses are runs of 1-3 s with a doubtful head
    # near the person: EVALUATION.md, change 14; across the time between two linked tracks too,
    # up to stitch_gap_s: change 27; the height gate rather than 10 cm: change 28)
    fill_m: float = 0.35
    fill_span_s: float = 6.0
    # a track must be seen this many times, this surely on average, to be reported (stereo
    # noise makes short-lived or doubtful heads)
    min_detections: int = 5
    min_track_confidence: float = 0.55
    # head model (adult anthropometry): the head's centre below the top of the head, and the eye
    # in front of and above that centre, in the head's own frame
    crown_to_centre_m: float = 0.11
    eye_forward_m: float = 0.13
    eye_up_m: float = 0.03
    # the gaze: staff who face a raised surface (the table, the back table) look at its middle
    # along their facing; walkers look slightly down
    work_surface_min_m: float = 0.6
    work_surface_max_m: float = 1.45
    gaze_reach_m: float = 2.2
    default_pitch_deg: float = 9.0
    # ... and one standing still with no raised surface seen in front (hidden from the cameras
    # by their own arms, the drapes or a neighbour, who stand over it) looks at their hands:
    # work height (an OR table is set near the elbow, about 1 m for adult staff) at a forearm
    # and hand's reach in front (EVALUATION.md, "People from the recording", facing changes)
    work_height_m: float = 1.0
    work_reach_m: float = 0.7
    # a standing person faces into the group: the middle of the others standing within
    # group_radius_m says which side is the front as strongly as arms reaching group_weight_m
    # further out on that side, where they stand with group_min_people - 1 others or more (a
    # pair stands side by side or back to back as often as face to face; round three or more the
    # middle of the others is the space they share)
    group_radius_m: float = 2.0
    group_weight_m: float = 0.3
    group_min_people: int = 3
    # ... and at least ospace_min_people of a group, whose shoulder lines' normals (pooled over
    # ospace_window_s: a team's shared point stays put for seconds) pass within
    # ospace_angle_deg of one point ospace_reach_m or nearer, face that point and look at it
    # down to work_height_m (pose.ospace_points; EVALUATION.md, facing changes)
    ospace_min_people: int = 3
    ospace_window_s: float = 4.0
    ospace_angle_deg: float = 60.0
    ospace_reach_m: float = 1.6
    # facing is smoothed over this many seconds (heads turn, but not between two stereo sets)
    facing_smooth_s: float = 1.0
    # a track moving faster than this faces where it goes
    walking_speed_m_s: float = 0.3
    fov_deg: float = 90.0

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ReconstructConfigError(f"PeopleConfig.{f.name}={value!r}: give a number")
            if not math.isfinite(value) or value < 0:
                raise ReconstructConfigError(
                    f"PeopleConfig.{f.name}={value!r}: must be a finite number >= 0"
                )
        if not 0 < self.cell_m <= 0.2:
            raise ReconstructConfigError(f"PeopleConfig.cell_m={self.cell_m!r}: give 0-0.2 m")
        if self.head_top_min_m >= self.head_top_max_m:
            raise ReconstructConfigError(
                f"PeopleConfig.head_top_min_m={self.head_top_min_m!r} must be below "
                f"head_top_max_m={self.head_top_max_m!r}"
            )
        if not 0 < self.head_isolation_min <= 1:
            raise ReconstructConfigError(
                f"PeopleConfig.head_isolation_min={self.head_isolation_min!r}: give 0-1"
            )
        if self.column_fill_share > self.min_column_share:
            raise ReconstructConfigError(
                f"PeopleConfig.column_fill_share={self.column_fill_share!r} must be at most "
                f"min_column_share={self.min_column_share!r}"
            )
        if not 1 <= self.confirm_seen <= self.confirm_timestamps:
            raise ReconstructConfigError(
                f"PeopleConfig.confirm_seen={self.confirm_seen!r} must be 1.."
                f"confirm_timestamps={self.confirm_timestamps!r}"
            )
        if not 0 < self.ospace_angle_deg <= 90:
            raise ReconstructConfigError(
                f"PeopleConfig.ospace_angle_deg={self.ospace_angle_deg!r}: give 0-90"
            )
        if not 1 < self.fov_deg < 179:
            raise ReconstructConfigError(f"PeopleConfig.fov_deg={self.fov_deg!r}: give 1-179")
