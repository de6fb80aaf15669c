"""The report made from its inputs, in the order the page reads: the case's facts, the review
outputs (each checked against the case's session), the pictures, the timeline, the page."""

from __future__ import annotations

import datetime as dt
import logging
import shlex
from collections.abc import Callable
from pathlib import Path

from protocol.sealing import Identity
from reconstructor.replay.models import CaseModels
from reconstructor.replay.observed_case import CaseObserved
from reconstructor.replay.path import CameraPath
from reconstructor.replay.run import case_raster
from reconstructor.replay.session_check import CaseInputs
from reconstructor.report.facts import read_facts
from reconstructor.report.page import PageInputs, render_page
from reconstructor.report.reviews import read_sightline, read_sterile
from reconstructor.report.timeline import timeline_png
from reconstructor.report.views import event_still, open_real, role_shares, role_thumbs

log = logging.getLogger(__name__)


def not_run_commands(case: Path, session: Path) -> dict[str, str]:
    """Per section, the command that makes its input (shown when it was not given)."""
    c = shlex.quote(str(case))
    return {
        "sterile": f"egosurg sterile {c} --field field.toml --roles roles.toml "
        "--sterile-roles surgeon,assistant,nurse_scrub --out sterile/",
        "sightline": f"egosurg sightline {c} --viewer anaesthetist --roles roles.toml "
        "--target monitor-a --site site.toml --out sightline/",
        "roles": f"egosurg sim roles {shlex.quote(str(session))} --out roles.toml writes the "
        "simulator's; a real room's come from its people tracking",
    }


def build_report(
    folder: Path, *, roles: str | None, sterile: str | None, sightlines: list[str],
    times: Callable[..., list[float]], zone: dt.tzinfo, identity: Identity | None,
    command: str,
) -> tuple[str, bool]:  # fmt: skip
    """(the page's HTML, whether a sealed session was read without its identity)."""
    facts = read_facts(folder, identity, zone)
    inputs = CaseInputs(folder)
    models = CaseModels(folder, identity)
    paths = [CameraPath(t) for t in inputs.trajectories(roles)] if roles else []
    sterile_review = read_sterile(sterile, inputs) if sterile else None
    sight_reviews = [read_sightline(s, inputs) for s in sightlines]
    thumb_times = times(facts, models)
    real, real_note = None, ""
    if facts.sealed:
        real_note = "sealed session: real frames need --identity"
    else:
        real = open_real(models, identity, facts.clock)
        if real is None:
            real_note = f"the session {facts.session_path} is gone: no real frames"
    try:
        observed = CaseObserved(folder, case_raster(folder))
        log.info("rendering %d role(s) at %d time(s)", len(paths), len(thumb_times))
        thumbs = role_thumbs(models, paths, thumb_times, real, observed)
        uncovered = [t for t in thumb_times if paths and t not in {th.t_s for th in thumbs}]
        shares, measured = role_shares(models, paths, observed)
        stills = {}
        if real is not None and sterile_review is not None:
            for e in (c for c in sterile_review.contacts if not c.camera_still):
                still = event_still(real, e.contact_m, e.peak_t_s)  # an older sterile run's
                if still is not None:
                    stills[e.number] = still
    finally:
        if real is not None:
            real.close()
    done = [e.t_s for e in models.entries]
    missing = [e.t_s for e in models.all_entries if e.status != "done"]
    picture = timeline_png(facts.clock, facts.span_s, done, missing, sterile_review,
                           sight_reviews, thumb_times if paths else [])  # fmt: skip
    page = PageInputs(
        facts=facts, timeline_png=picture, sterile=sterile_review, sightlines=sight_reviews,
        thumbs=thumbs, shares=shares, share_timestamps=measured, roles_file=roles,
        event_stills=stills, real_note=real_note, command=command, uncovered_times=uncovered,
        generated=dt.datetime.now(zone).strftime("%Y-%m-%d %H:%M %Z"),
        not_run=not_run_commands(folder, facts.session_path),
    )  # fmt: skip
    return render_page(page), facts.sealed
