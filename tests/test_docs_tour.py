"""README.md's tour runs as written from an empty folder (issue 49: a new user types it line by line).

Each line through the shell, in a fresh folder, with the `flockcal` this interpreter installs, then what each
line's comment promises read from the files it made. It runs every command the tour shows but `serve`
(a service that runs until stopped: its streams are tested in tests/test_server_streams.py): about 20 s of
CPU, the simulations and the Dask cluster most of it. tests/test_docs_site.py checks the lines parse.
"""

from __future__ import annotations

import json
import os
import shlex
import subprocess
import sys
from pathlib import Path

from test_docs_site import fenced_lines, section

# Long-running lines the tour shows but this test does not run, and where they are tested instead.
NOT_RUN = {"serve": "a live service until Ctrl-C: its VRPN and VMC streams are tests/test_server_streams.py's"}


def test_the_tour_runs_as_written_from_an_empty_folder(tmp_path):
    # Tried: each tour line as README.md writes it, through the shell (its redirections too), in an empty
    # folder, one after another as a new user types them, with the `flockcal` this interpreter installs; then
    # what each line's comment promises, read from the files they made. `serve` runs until stopped (NOT_RUN).
    lines = [ln for ln in fenced_lines(section("A tour")) if ln.startswith("flockcal ")]
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}",
           "HOME": str(tmp_path / "home"), "XDG_DATA_HOME": str(tmp_path / "home" / "data")}
    work = tmp_path / "tour"
    work.mkdir()
    ran, truth = [], None
    for line in lines:
        words = shlex.split(line, comments=True)
        if words[1] in NOT_RUN:
            continue
        run = subprocess.run(["bash", "-c", f"set -o pipefail; {line}"], cwd=work, env=env, capture_output=True,
                             text=True, timeout=240)
        assert run.returncode == 0, f"README's tour line {line!r} failed (exit {run.returncode}):\n{run.stderr[-2000:]}"
        ran.append(words[1])
        if truth is None and (work / "take.truth.json").exists():
            truth = (work / "take.truth.json").read_bytes()  # the sensor take's, which later lines must keep
    assert {"simulate", "fit", "report", "fit-markers", "batch"} <= set(ran), ran

    fit = json.loads((work / "fit.json").read_text())
    assert fit["humanoid"] and set(fit["humanoid"]) == set(fit["sensors"]), "fit.json has no humanoid"
    assert (work / "take.bvh").read_text().splitlines()[1] == "ROOT Hips"
    glb = (work / "take.glb").read_bytes()
    assert glb[:4] == b"glTF" and b"VRMC_vrm" in glb[:200_000], "take.glb is not a VRM"
    assert (work / "take.trc").read_text().startswith("PathFileType")
    assert "<html" in (work / "report.html").read_text(encoding="utf-8")[:2000].lower()
    assert (work / "take.truth.json").read_bytes() == truth, "a later tour line overwrote take.npz's truth"
    markers = json.loads((work / "markers.json").read_text())
    assert len(markers["bodies"]) >= 10 and markers["joints"], "fit-markers found no skeleton in markers.c3d"
    takes = sorted(p.name for p in (work / "archive").glob("*.npz"))
    assert len(takes) >= 2 and takes[0] == "take01.npz", takes
    assert json.loads((work / "results" / "combined.json").read_text())["bones"], "batch --combine made no bones"
