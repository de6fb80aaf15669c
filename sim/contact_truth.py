"""The true contact intervals of a simulated case: when some vertex of a person's body lies inside
a sterile field box (``sim/contact.py`` scripts the touch; ``egosurg sim contact`` writes these
intervals as the truth ``egosurg sterile`` is judged against)."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from protocol.formats.site import SiteBox
from sim.people import person_objects, person_state
from sim.room import SceneObject
from sim.world import World


def _bodies(world: World, t_s: float) -> dict[str, list[SceneObject]]:
    out = {p.name: person_objects(p, person_state(p, t_s)) for p in world.people_scripts}
    if world.contact is not None:
        out[world.contact.person.name] = world.contact.objects(t_s)
    return out


def _inside(objects: list[SceneObject], box: SiteBox) -> bool:
    return any(bool(np.any(box.contains(o.mesh.vertices))) for o in objects)


def true_field_intervals(
    world: World, box: SiteBox, t0_s: float, t1_s: float, step_s: float = 0.05
) -> list[tuple[str, float, float]]:
    """(person, start_s, end_s) of every interval in [t0_s, t1_s] during which some vertex of
    that person's body lies inside ``box``, in start order; edges to 1 ms."""
    times = np.arange(t0_s, t1_s + 1e-9, step_s)
    flags: dict[str, list[bool]] = {}
    for t in times:
        for name, objs in _bodies(world, float(t)).items():
            flags.setdefault(name, []).append(_inside(objs, box))

    def edge(name: str, a: float, b: float, inside_at_a: bool) -> float:
        while b - a > 1e-3:  # the state flips between a and b
            m = (a + b) / 2
            if _inside(_bodies(world, m)[name], box) == inside_at_a:
                a = m
            else:
                b = m
        return (a + b) / 2

    out = []
    for name, f in flags.items():
        start = float(times[0]) if f[0] else None
        for k in range(1, len(f)):
            if f[k] and not f[k - 1]:
                start = edge(name, float(times[k - 1]), float(times[k]), False)
            elif f[k - 1] and not f[k] and start is not None:
                out.append((name, start, edge(name, float(times[k - 1]), float(times[k]), True)))
                start = None
        if start is not None:
            out.append((name, start, float(times[-1])))
    return sorted(out, key=lambda r: r[1])


def write_truth_csv(path: Path, rows: list[tuple[str, float, float]]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["person", "start_s", "end_s"])
        for name, a, b in rows:
            w.writerow([name, f"{a:.3f}", f"{b:.3f}"])
