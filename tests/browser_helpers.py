"""Debian's chromium for the page tests: where it is, how it is started headless (software GL, so the
dashboard's WebGL view draws without a GPU), and the marker that skips a module where it is missing."""

from __future__ import annotations

import os

import pytest

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
                 "--disable-sync", "--no-first-run", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
NEEDS_CHROMIUM = pytest.mark.skipif(not os.path.exists(CHROMIUM),
                                    reason=f"needs Debian's chromium at {CHROMIUM} (apt-get install chromium)")


def launch(playwright):
    """A headless chromium of this machine (playwright never downloads one here)."""
    return playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
