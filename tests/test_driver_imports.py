"""The layers' imports hold: the driver knows no simulator (nor solver, nor server), the rotation module
imports no other layer, and sim:// exists only once a program has imported the simulator package."""

from __future__ import annotations

import subprocess
import sys
import textwrap


def run(code: str) -> subprocess.CompletedProcess:
    # A fresh interpreter: this test process has long imported every layer.
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, timeout=60)


def test_the_driver_and_the_rotation_module_import_no_other_layer():
    out = run("""
        import sys
        import flockcal.rotations
        assert not [m for m in sys.modules if m.startswith(("flockcal.drivers", "flockcal.simulator",
                    "flockcal.solver", "flockcal.server"))], "flockcal.rotations pulled in another layer"
        import flockcal.drivers.reader, flockcal.drivers.recording, flockcal.drivers.link
        others = sorted(m for m in sys.modules if m.startswith(("flockcal.simulator", "flockcal.solver",
                                                               "flockcal.server")))
        assert not others, others
        print("ok")
    """)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr


def test_sim_urls_open_only_after_the_simulator_package_is_imported():
    # What was tried: a sim:// URL through the driver's link in a program that never imported the
    # simulator (a clear error naming the URL), then the same after `import flockcal.simulator`.
    out = run("""
        from flockcal.drivers.link import FlockLink, TrackerError
        url = "sim://imports?birds=2"
        try:
            FlockLink(url).open()
        except TrackerError as exc:
            print("refused:", exc)
        import flockcal.simulator
        link = FlockLink(url).open()
        print("opened:", type(link.port).__module__, link.port.performer.names)
        link.close()
    """)
    assert out.returncode == 0, out.stderr
    refused, opened = out.stdout.strip().splitlines()
    assert refused.startswith("refused: cannot open sim://imports?birds=2") and "sim" in refused
    assert opened == "opened: flockcal.simulator.protocol_sim ('pelvis', 'chest')"
