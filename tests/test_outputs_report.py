"""HTML report (issue 8, part 4): `flockcal report` writes one self-contained page whose figures,
tables, topology and slip events render in a real browser."""

from __future__ import annotations

import re

import pytest

from flockcal.cli import main
from flockcal.simulator.take import simulate
from flockcal.takes import save_take

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
    "--disable-sync", "--no-first-run",
]  # fmt: skip
SLIPPED = "r_forearm"


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    """A report of a 10-sensor take in which one sensor slides 3 cm half-way through."""
    folder = tmp_path_factory.mktemp("report")
    take, _ = simulate(
        "human", "exercise", seconds=24, rate_hz=60, seed=3, birds=10,
        faults={"slip": {"sensor": SLIPPED, "distance_m": 0.03, "at_time": 14.0}},
    )  # fmt: skip
    save_take(folder / "take.npz", take)
    assert main(["report", str(folder / "take.npz"), "-o", str(folder / "report.html")]) == 0
    return folder / "report.html", take


def test_report_is_one_file_with_embedded_figures_and_no_external_references(report):
    path, take = report
    text = path.read_text()
    srcs = re.findall(r'src="([^"]*)"', text)
    assert len(srcs) >= 3 and all(s.startswith("data:image/png;base64,") for s in srcs)
    assert not re.search(r'(href|src)="(?!data:)', text)  # nothing to fetch: the page stands alone
    for section in ("Skeleton", "Topology", "Bones", "Residuals over time", "Residual magnitude histograms",
                    "Coverage of the data", "Slip events"):  # fmt: skip
        assert f"<h2>{section}</h2>" in text
    assert all(name in text for name in take.names)


@pytest.mark.browser
def test_report_renders_in_headless_chromium_with_every_image_decoded(report):
    from playwright.sync_api import sync_playwright

    path, take = report
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            page = browser.new_page()
            page.goto(path.as_uri())
            page.wait_for_load_state("load")
            images = page.evaluate(
                "Array.from(document.images).map(i => ({alt: i.alt, w: i.naturalWidth, h: i.naturalHeight, ok: i.complete}))"
            )
            bone_rows = page.locator("h2:text('Bones') + table tr").count()
            tree_items = page.locator("ul.tree li").count()
            slip_text = page.locator("h2:text('Slip events') + table").inner_text()
        finally:
            browser.close()
    assert {i["alt"] for i in images} >= {"skeleton drawing", "residuals over time", "residual histograms"}
    assert all(i["ok"] and i["w"] > 100 and i["h"] > 100 for i in images)
    assert bone_rows > take.n_sensors - 1  # header + at least one bone per non-root body
    assert tree_items == take.n_sensors
    assert SLIPPED in slip_text


def test_report_shows_the_services_progress_and_draws_no_bone_to_an_undetermined_joint(tmp_path):
    from flockcal.solver.progress import progress_of
    from flockcal.solver.accumulator import GramAccumulator
    from flockcal.solver.calibration import calibrate

    # Tried: 4 s of the kiosk routine, which moves the left leg only: most joints are not determined yet.
    take, _ = simulate("human", "kiosk", seconds=4, rate_hz=60, seed=5, birds=16)
    save_take(tmp_path / "take.npz", take)
    assert main(["report", str(tmp_path / "take.npz"), "-o", str(tmp_path / "report.html")]) == 0
    text = (tmp_path / "report.html").read_text()
    acc = GramAccumulator(take.n_sensors)
    acc.add_poses(take.rotations, take.positions, take.valid)
    doc = progress_of(calibrate(acc, names=list(take.names)).to_dict(), 0.005 / 2**0.5, 0.005).to_dict()
    assert not doc["done"] and doc["missing"]
    assert "<h2>Calibration progress</h2>" in text
    assert f"{doc['joints_done']} of {doc['joints_needed']} joints calibrated ({doc['percent']} %)" in text
    assert "<b>not done</b>" in text
    for m in doc["missing"]:
        assert m["label"] in text and m["why"] in text.replace("&#x27;", "'")
