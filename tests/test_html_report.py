"""report.html: one self-contained page, every image decodes, a failing scenario has its
error-vs-time plot; drawn from the verdict's kept series, not by re-running."""

import base64
import io
import re
from html.parser import HTMLParser

import matplotlib.image
import numpy as np
import pytest

from conftest import REPORT_SCENARIOS
from mjxdiff.compare import verdict


class _Page(HTMLParser):
    def __init__(self):
        super().__init__()
        self.images, self.links, self.ids = [], [], set()

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "img":
            self.images.append(a)
        if tag in ("a", "link", "script") and (a.get("href") or a.get("src")):
            self.links.append(a.get("href") or a.get("src"))
        if "id" in a:
            self.ids.add(a["id"])


def test_the_page_is_self_contained_and_every_image_decodes(two_sweeps):
    root, _ = two_sweeps
    page = _Page()
    page.feed((root / "bugged" / "report.html").read_text())
    assert page.images, "no images"
    for img in page.images:
        assert img["src"].startswith("data:image/png;base64,"), img["src"][:40]  # nothing to fetch
        pixels = matplotlib.image.imread(io.BytesIO(base64.b64decode(img["src"].split(",", 1)[1])), format="png")
        assert pixels.shape[0] > 50 and pixels.shape[1] > 50 and np.ptp(pixels) > 0  # drawn, not blank
    # links go to anchors in the page or to files beside it, never to a server
    assert all(not re.match(r"[a-z]+://", href) for href in page.links), page.links


def test_each_failing_field_has_its_error_vs_time_plot(two_sweeps):
    root, _ = two_sweeps
    page = _Page()
    page.feed((root / "bugged" / "report.html").read_text())
    alts = {img["alt"] for img in page.images}
    assert "pass rate per scenario" in alts
    for name in ("pendulum", "cartpole"):  # the two the gain slip breaks
        assert f"{name} qpos error vs time" in alts and f"{name} qvel error vs time" in alts
        assert name in page.ids
    assert not any(a.startswith("double_pendulum ") for a in alts)  # passing: plots only on request


def test_a_passing_page_says_what_was_tested_and_links_only_to_what_it_holds(two_sweeps):
    """issue 51: the page of a clean sweep said 'first step -1', linked each scenario to a
    section it did not have, and said nothing of the batch, the steps or what was randomized."""
    root, _ = two_sweeps
    html = (root / "clean" / "report.html").read_text()
    page = _Page()
    page.feed(html)
    anchors = [href[1:] for href in page.links if href.startswith("#")]
    assert all(a in page.ids for a in anchors), (anchors, page.ids)
    rows = re.findall(r"<tr><td>(?:<a [^>]*>)?([^<]+)(?:</a>)?</td><td class='pass'>pass</td><td>([^<]*)</td>", html)
    assert len(rows) == len(REPORT_SCENARIOS), rows
    for name, tested in rows:
        assert re.match(r"\d+ members x \d+ steps; randomized: state, controls", tested), (name, tested)
        assert "checks: one-step, host interface" in tested, tested
    assert "<td>-1</td>" not in html


def test_the_kept_series_is_the_batch_max_error_with_its_bound():
    err = np.array([0.0, 1.0, 5.0, 2.0, 3.0, 9.0, 1.0])
    bound = np.array([1.0, 1.0, 1.0, 2.0, 2.0, 2.0, 4.0])
    rows = verdict.downsample(err, bound, most=3)
    assert [r[0] for r in rows] == [0, 2, 4]  # windows [0, 2), [2, 4), [4, 7)
    assert [r[1] for r in rows] == [1.0, 5.0, 9.0] and [r[2] for r in rows] == [1.0, 2.0, 4.0]
    assert verdict.downsample(err, bound) == tuple((k, float(e), float(b)) for k, (e, b) in enumerate(zip(err, bound)))


def _browser():
    import shutil

    return next((shutil.which(b) for b in ("chromium", "chromium-browser", "google-chrome") if shutil.which(b)), None)


@pytest.mark.skipif(_browser() is None, reason="no headless Chromium here (.ci/run installs it where apt can)")
def test_a_real_browser_shows_the_plots(two_sweeps, tmp_path):
    """Headless Chromium renders the page offline: the first-exceedance line's orange, drawn
    only inside the embedded plots, is on screen."""
    import subprocess

    root, _ = two_sweeps
    shot = tmp_path / "shot.png"
    subprocess.run([_browser(), "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                    f"--screenshot={shot}", "--window-size=1100,2400", (root / "bugged" / "report.html").as_uri()],
                   check=True, capture_output=True, timeout=120)
    rgb = (matplotlib.image.imread(shot)[..., :3] * 255).round().astype(int)
    orange = np.all(np.abs(rgb - [0xE6, 0x7E, 0x22]) <= 2, axis=-1)
    assert orange.sum() > 50, "no plot on screen"
