"""The studio in a real browser: Debian's Chromium driven headless by Playwright."""

from __future__ import annotations

import os
import re
import shutil
from pathlib import Path

import pytest

from tests.test_app_api import REPO, scene_image, start_studio, write_bad_inputs

CHROMIUM = shutil.which("chromium")
SCREENSHOTS = REPO / "test-output" / "ui"
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--no-first-run", "--disable-quic"]
TIMEOUT_MS = 60_000

# Outside CI a machine without Chromium skips these (`bash scripts/setup.sh --test` installs it);
# in CI (CI=true) they always run, so a missing browser fails loudly instead of passing silently.
pytestmark = pytest.mark.skipif(CHROMIUM is None and not os.environ.get("CI"),
                                reason="Debian's chromium is not installed; run bash scripts/setup.sh --test")


@pytest.fixture(scope="module")
def app_url(tmp_path_factory):
    demo, url, _ = start_studio(tmp_path_factory.mktemp("browser"), examples_dir=REPO / "examples")
    yield url
    demo.close()


@pytest.fixture(scope="module")
def browser():
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        chromium = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        yield chromium
        chromium.close()


def image_src(page, elem_id: str) -> str | None:
    img = page.locator(f"#{elem_id} img")
    return img.first.get_attribute("src") if img.count() else None


def upload_input(page, path: Path) -> None:
    page.locator("#input-file input[type=file]").set_input_files(str(path))


def clear_input(page) -> None:
    page.locator("#input-file").get_by_role("button", name=re.compile("clear", re.I)).first.click()
    page.wait_for_selector("#input-file input[type=file]", state="attached")


def error_toasts(page) -> list[str]:
    return page.locator(".toast-body.error").all_inner_texts()


def test_upload_pick_rotate_run(browser, app_url, tmp_path):
    SCREENSHOTS.mkdir(parents=True, exist_ok=True)
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    page.set_default_timeout(TIMEOUT_MS)
    page.goto(app_url)
    page.wait_for_selector("#run")

    upload_input(page, scene_image(tmp_path / "scene.png", size=(128, 96)))
    page.wait_for_selector("#input-preview img")
    page.wait_for_function("() => document.querySelector('#estimate').innerText.includes('About')")

    # Pick a probe from the gallery: the selection and the light preview follow.
    page.locator("#probe-gallery button.thumbnail-item").nth(1).click()
    page.wait_for_function("() => document.querySelector('#light-preview img') !== null")
    before = image_src(page, "light-preview")

    # Move the rotation slider: the preview is re-rendered.
    page.locator("#rotation input[type=range]").fill("45")
    page.wait_for_function(
        "(old) => { const img = document.querySelector('#light-preview img'); return img && img.src !== old; }",
        arg=before)

    page.locator("#run").click()
    page.wait_for_function("() => document.querySelector('#status').innerText.includes('Done')")
    assert image_src(page, "out-relit") and image_src(page, "out-albedo")
    assert page.locator("#downloads a").count() == 3
    page.wait_for_function("() => !document.querySelector('#light-preview').innerText.includes('processing')")
    page.screenshot(path=str(SCREENSHOTS / "studio-1280x800.png"), full_page=True)
    assert error_toasts(page) == []

    page.set_viewport_size({"width": 420, "height": 900})
    page.wait_for_timeout(300)
    page.screenshot(path=str(SCREENSHOTS / "studio-narrow-420.png"), full_page=True)
    page.close()


def test_bad_upload_shows_a_readable_error_and_the_page_keeps_working(browser, app_url, tmp_path):
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    page.set_default_timeout(TIMEOUT_MS)
    page.goto(app_url)
    page.wait_for_selector("#run")
    bad = write_bad_inputs(tmp_path)

    upload_input(page, bad["fake_video"])
    page.wait_for_selector(".toast-body.error")
    assert any("fake.mp4" in text for text in error_toasts(page))
    page.screenshot(path=str(SCREENSHOTS / "studio-bad-upload.png"))

    assert not any("/tmp/" in text for text in error_toasts(page))  # no server paths shown

    # Uploads over the size limit are refused in the browser with a message of their own.
    page.locator(".toast-close").first.click()
    clear_input(page)
    upload_input(page, bad["big"])
    page.wait_for_function("() => [...document.querySelectorAll('.toast-body')]"
                           ".some(t => /size|large/i.test(t.innerText))")

    if page.locator("#input-file input[type=file]").count() == 0:
        clear_input(page)
    upload_input(page, scene_image(tmp_path / "scene.png"))
    page.wait_for_selector("#input-preview img")
    page.locator("#run").click()
    page.wait_for_function("() => document.querySelector('#status').innerText.includes('Done')")
    page.close()


def test_examples_show_cached_results_instantly(browser, app_url):
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    page.set_default_timeout(TIMEOUT_MS)
    page.goto(app_url)
    page.wait_for_selector("#run")
    page.get_by_text("Objects under a sunset").first.click()
    page.wait_for_function("() => document.querySelector('#status').innerText.includes('Cached example')",
                           timeout=10_000)
    assert image_src(page, "out-relit") and image_src(page, "out-albedo")
    assert page.locator("#probe-name input").input_value() == "sunset"
    assert error_toasts(page) == []
    page.close()
