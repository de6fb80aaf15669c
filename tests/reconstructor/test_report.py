"""``egosurg report``: the case report a review team reads offline, on a tiny reconstructed case
(the intraoperative sim's sets at 2.0-2.2 s, three timestamps) with the real ``egosurg sim
roles``, ``egosurg sightline`` and ``egosurg sterile`` outputs made for it.

What a user relies on:
- the file opens in a real browser (headless Chromium) without a single request leaving the
  file: every picture is in it, every picture loads, and it prints to PDF;
- it names the case, its date and time of day (the sim's session starts 2026-01-01 00:00 UTC,
  so case time 2.0 s reads 01:00:02.000 in Berlin), the health of each camera as the session
  recorded it (15 fps: the eval set's rate), the line-of-sight answers, each role's view beside
  a real camera, and the observed share per role;
- an input not given makes its section say "not run" with the command that makes it;
- a sealed session without its identity gives a report without real frames that says so;
- bad input (not a case, a roles file or review output of another session, a time outside the
  case) is one line and exit status 2.
"""

from __future__ import annotations

import base64
import csv
import json
import shutil
import stat
from html.parser import HTMLParser
from pathlib import Path

import pytest

from tests.browser import CHROMIUM_MISSING, SKIP_REASON, HeadlessChromium
from tests.helpers import egosurg_in_process, run_egosurg
from tests.reconstructor.tiny import tiny_config_toml, tiny_eval_session

ROLES = ("surgeon", "assistant", "anaesthetist", "nurse_scrub", "circulator", "robot_assistant")


@pytest.fixture(scope="module")
def case(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("report")
    h5 = tiny_eval_session(root, sets=4) / "session.h5"
    (root / "tiny.toml").write_text(tiny_config_toml(3))
    done = run_egosurg("reconstruct", str(h5), "--config", str(root / "tiny.toml"),
                       "--every", "0.0667s", "--out", str(root / "case"), timeout=300)  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    roles = run_egosurg("sim", "roles", str(h5), "--every", "0.05", "--out",
                        str(root / "roles.toml"), "--site-out",
                        str(root / "site.toml"))  # fmt: skip
    assert roles.returncode == 0, roles.stderr
    from protocol.cli import main

    assert main(["sightline", str(root / "case"), "--viewer", "anaesthetist", "--roles",
                 str(root / "roles.toml"), "--target", "monitor-b", "--site",
                 str(root / "site.toml"), "--out", str(root / "los")]) == 0  # fmt: skip
    assert main(["sterile", str(root / "case"), "--field", str(root / "site.toml"), "--roles",
                 str(root / "roles.toml"), "--out", str(root / "sterile")]) == 0  # fmt: skip
    return {"root": root, "case": root / "case", "roles": root / "roles.toml",
            "los": root / "los", "sterile": root / "sterile", "session": h5}  # fmt: skip


class Page(HTMLParser):
    """The tags that could fetch something: every src and href, and any <script>/<link>."""

    def __init__(self, text: str) -> None:
        super().__init__()
        self.sources: list[tuple[str, str]] = []  # (tag, url)
        self.tags: list[str] = []
        self.feed(text)

    def handle_starttag(self, tag: str, attrs) -> None:
        self.tags.append(tag)
        for k, v in attrs:
            if k in ("src", "href", "srcset", "poster", "data") and v:
                self.sources.append((tag, v))


def _full_report(case, capsys, out: Path, *extra: str) -> str:
    code, stdout, err = egosurg_in_process(
        capsys, "report", str(case["case"]), "--roles", str(case["roles"]), "--sightline",
        str(case["los"]), "--sterile", str(case["sterile"]), "--timezone", "Europe/Berlin",
        "--out", str(out), *extra,
    )  # fmt: skip
    assert code == 0, err[-2000:]
    assert stdout.strip() == f"wrote {out} (contains patient imagery)"
    return out.read_text()


@pytest.mark.skipif(CHROMIUM_MISSING, reason=SKIP_REASON)
def test_the_report_opens_offline_in_chromium_every_picture_loads_and_it_prints(
    case, capsys, tmp_path
):
    out = tmp_path / "report.html"
    text = _full_report(case, capsys, out, "--times", "2.0")
    assert stat.S_IMODE(out.stat().st_mode) == 0o600  # it shows the patient: owner-only
    page = Page(text)
    assert "script" not in page.tags and "link" not in page.tags and "iframe" not in page.tags
    assert page.sources and all(url.startswith("data:image/") for _, url in page.sources)
    browser = HeadlessChromium(tmp_path / "profile", (1150, 900))
    try:
        browser.call("Network.enable")
        browser.call("Page.enable")
        browser.call("Page.navigate", url=out.as_uri())
        browser.wait_for("Page.loadEventFired", timeout_s=60)
        images = browser.evaluate(
            "Array.from(document.images).map(i => [i.alt, i.complete, i.naturalWidth])"
        )
        body = browser.evaluate("document.body.innerText")
        pdf = base64.b64decode(browser.call("Page.printToPDF", timeout_s=120)["data"])
        requests = [e["params"]["request"]["url"] for e in browser.events
                    if e["method"] == "Network.requestWillBeSent"]  # fmt: skip
    finally:
        browser.close()
    # nothing but the file itself and its own data: URIs
    assert [u for u in requests if not u.startswith("data:")] == [out.as_uri()]
    assert all(done and width > 0 for _, done, width in images), images
    alts = [a for a, _, _ in images]
    # the timeline, the sightline's two worst instants, and each role beside a real camera
    assert "timeline of the case" in alts and sum(a.startswith("worst_") for a in alts) == 2
    for role in ROLES:
        assert f"{role} view" in alts and f"{role} nearest real camera" in alts
    assert pdf.startswith(b"%PDF-") and pdf.count(b"/Type /Page\n") + pdf.count(b"/Type/Page") >= 1
    # what the page says: the case, its day and time of day, each camera's health
    assert "Case report: sim-intraoperative-seed3" in body and "2026-01-01" in body
    assert "01:00:02.000 CET (case time 2.000 s" in body  # Berlin is UTC+1 on 1 January
    from protocol.session import SessionReader

    with SessionReader(case["session"]) as reader:
        serials = reader.info.camera_serials
    for serial in serials:
        assert f"SN{serial}\tsim-eval-set\tSVGA 960x600 @ 15 fps\t4\t15.00\t0\tnone" in body
    assert "anaesthetist sees monitor-b" in body
    for role in ROLES:  # the observed-versus-inferred table: one row per role, 3 timestamps
        assert f"\n{role}\t3\t" in body


def test_inputs_not_given_say_not_run_with_the_command_that_makes_them(case, capsys, tmp_path):
    out = tmp_path / "bare.html"
    code, _, err = egosurg_in_process(capsys, "report", str(case["case"]), "--out", str(out))
    assert code == 0, err[-2000:]
    text = out.read_text()
    for section, command in (("sterile", "egosurg sterile"), ("sightline", "egosurg sightline"),
                             ("views", "--roles roles.toml")):  # fmt: skip
        part = text.split(f'<h2 id="{section}">')[1].split("<h2")[0]
        assert "Not run" in part and command in part, part
    assert "<img" in text.split('<h2 id="timeline">')[1].split("<h2")[0]  # the case's timestamps


def test_each_contact_shows_its_evidence_and_the_real_camera_nearest_it(case, capsys, tmp_path):
    """A sterile output with one contact (its row and render as ``egosurg sterile`` writes
    them): the event's render and the real camera nearest the contact are in the report."""
    folder = tmp_path / "sterile"
    shutil.copytree(case["sterile"], folder)
    with (case["sterile"] / "events.csv").open() as fh:
        header = next(csv.reader(fh))
    render = next(case["los"].glob("worst_*.png"))  # any picture stands for the render
    shutil.copy(render, folder / "event_001.png")
    row = {k: "" for k in header} | {
        "event": "1", "field": "monitor-b", "kind": "contact", "role": "circulator",
        "role_distance_m": "0.20", "start_s": "2.067", "end_s": "2.133", "timestamps": "2",
        "peak_t_s": "2.067", "peak_points": "12", "contact_x_m": "0.5", "contact_y_m": "0.2",
        "contact_z_m": "1.0", "viewpoint": "ring 0 deg", "unoccluded_fraction": "0.80",
        "render": "event_001.png",
    }  # fmt: skip
    with (folder / "events.csv").open("a", newline="") as fh:
        csv.DictWriter(fh, header).writerow(row)
    out = tmp_path / "events.html"
    code, _, err = egosurg_in_process(capsys, "report", str(case["case"]), "--sterile", str(folder),
                           "--timezone", "UTC", "--out", str(out))  # fmt: skip
    assert code == 0, err[-2000:]
    part = out.read_text().split('<h2 id="sterile">')[1].split("<h2")[0]
    assert "1 contact event(s)" in part and "Event 1: circulator in" in part
    assert "00:00:02.067 UTC" in part  # its time of day
    sources = dict(Page(part).sources)
    assert part.count('alt="event 1 event_001.png"') == 1 and part.count('alt="event 1 real') == 1
    assert base64.b64encode(render.read_bytes()).decode() in part  # the render, byte for byte
    assert sources and "nearest the contact: SN" in part
    # the sterile run's own still from the camera that saw the contact best, named in its row,
    # is shown with its clip named; the nearest camera's frame is then not repeated
    still = sorted(case["los"].glob("worst_*.png"))[-1]
    shutil.copy(still, folder / "event_001_camera.png")
    row |= {"camera": "SN7-left", "camera_still": "event_001_camera.png",
            "clip": "event_001_clip.mp4"}  # fmt: skip
    with (folder / "events.csv").open("w", newline="") as fh:
        writer = csv.DictWriter(fh, header)
        writer.writeheader()
        writer.writerow(row)
    code, _, err = egosurg_in_process(capsys, "report", str(case["case"]), "--sterile", str(folder),
                           "--timezone", "UTC", "--out", str(out))  # fmt: skip
    assert code == 0, err[-2000:]
    part = out.read_text().split('<h2 id="sterile">')[1].split("<h2")[0]
    assert base64.b64encode(still.read_bytes()).decode() in part
    assert "(SN7-left) recorded at the event" in part and "event_001_clip.mp4" in part
    assert 'alt="event 1 real' not in part


def test_a_sealed_session_without_its_identity_gives_a_report_without_real_frames(
    case, capsys, tmp_path, monkeypatch
):
    """A reviewer without the key still gets the case's structure and renders; the page says
    at its top what is missing and why, and the command says it on stderr. With the identity
    the real frames are there."""
    import numpy as np

    from protocol.formats.session_id import SessionId
    from protocol.formats.trajectory import read_trajectories, write_trajectories
    from protocol.sealing import generate_identity, write_identity
    from protocol.session import SessionReader
    from tests.helpers import copy_sets

    monkeypatch.delenv("EGOSURG_IDENTITY", raising=False)  # "without": not from the shell either
    key = generate_identity("hospital-a")
    _, identity = write_identity(key, tmp_path / "keys")
    sealed = tmp_path / "sealed.h5"
    with SessionReader(case["session"]) as reader:
        n, start = len(reader.sets().set_unix_ns), reader.info.started_unix_ns
    copy_sets(case["session"], sealed, np.arange(n), recipients=[key.recipient])
    folder = tmp_path / "case"
    shutil.copytree(case["case"], folder)
    index = json.loads((folder / "case.json").read_text())
    (folder / "case.json").write_text(json.dumps(index | {"session": str(sealed)}))
    roles = tmp_path / "roles.toml"  # the same people, made for the sealed copy ("copy")
    write_trajectories(roles, read_trajectories(case["roles"])[:1],
                       session=SessionId(name="copy", started_unix_ns=start))  # fmt: skip
    out = tmp_path / "sealed.html"
    args = ("report", str(folder), "--roles", str(roles), "--times", "2.0", "--out", str(out))
    code, _, err = egosurg_in_process(capsys, *args)
    assert code == 0, err[-2000:]
    assert "sealed and no --identity" in err
    text = out.read_text()
    assert 'id="sealed"' in text and "hospital-a" in text and 'real camera"' not in text
    code, _, err = egosurg_in_process(capsys, *args, "--identity", str(identity))
    assert code == 0, err[-2000:]
    text = out.read_text()
    assert 'id="sealed"' not in text and 'alt="surgeon nearest real camera"' in text


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (("--times", "9"), "--times: 9.000 s"),
        (("--times", "noon"), "neither case seconds"),
        (("--timezone", "Mars/Olympus"), "is not a time zone"),
        (("--sterile", "."), "no events.csv there"),
    ],
)
def test_bad_report_input_gets_one_clear_line(case, capsys, tmp_path, extra, message):
    code, _, err = egosurg_in_process(capsys, "report", str(case["case"]), *extra, "--out",
                           str(tmp_path / "r.html"))  # fmt: skip
    assert code == 2 and "Traceback" not in err, err
    (line,) = err.strip().splitlines()
    assert message in line
    assert not (tmp_path / "r.html").exists()


def test_not_a_case_and_files_of_another_session_are_refused_in_one_line(case, capsys, tmp_path):
    from tests.reconstructor.test_replay import _demo_style_session

    code, _, err = egosurg_in_process(
        capsys, "report", str(tmp_path), "--out", str(tmp_path / "r.html")
    )
    assert code == 2 and err.count("\n") == 1 and "is not a case folder" in err, err
    demo = _demo_style_session(tmp_path / "demo.h5")
    done = run_egosurg("sim", "roles", str(demo), "--every", "0.05", "--out",
                       str(tmp_path / "demo_roles.toml"))  # fmt: skip
    assert done.returncode == 0, done.stderr
    code, _, err = egosurg_in_process(capsys, "report", str(case["case"]), "--roles",
                           str(tmp_path / "demo_roles.toml"), "--out",
                           str(tmp_path / "r.html"))  # fmt: skip
    assert code == 2 and err.count("\n") == 1 and "made for session 'demo-or1'" in err, err
    los = tmp_path / "los"  # a sightline output whose record names the demo's session
    shutil.copytree(case["los"], los)
    record = (los / "made_for.toml").read_text()
    (los / "made_for.toml").write_text(record.replace("sim-intraoperative-seed3", "demo-or1"))
    code, _, err = egosurg_in_process(capsys, "report", str(case["case"]), "--sightline", str(los),
                           "--out", str(tmp_path / "r.html"))  # fmt: skip
    assert code == 2 and err.count("\n") == 1 and "made for session 'demo-or1'" in err, err
    assert not (tmp_path / "r.html").exists()
