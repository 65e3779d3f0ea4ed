"""Driving palette-studio in headless Chromium (Debian's ``chromium`` and ``chromium-driver``;
nothing is downloaded): open the page, type a colour into a picker, read viewport pixels."""

from __future__ import annotations

import shutil
import time

CHROMIUM, CHROMEDRIVER = shutil.which("chromium"), shutil.which("chromedriver")
MISSING = ("no browser: install Debian's chromium and chromium-driver "
           "(apt-get install chromium chromium-driver) to run the browser tests")

#: The viewport's WebGL canvas (viser keeps its drawing buffer), copied to read pixels.
_READ_PIXEL = """
const canvas = [...document.querySelectorAll('canvas')]
    .sort((a, b) => b.width * b.height - a.width * a.height)[0];
if (!canvas || canvas.width === 0) return null;
const copy = document.createElement('canvas');
copy.width = canvas.width; copy.height = canvas.height;
const context = copy.getContext('2d');
context.drawImage(canvas, 0, 0);
const x = Math.floor(arguments[0] * canvas.width), y = Math.floor(arguments[1] * canvas.height);
return Array.from(context.getImageData(x, y, 1, 1).data.slice(0, 3));
"""


def chromium(width: int = 1000, height: int = 700):
    """A headless Chromium under selenium, WebGL by SwiftShader (no GPU needed)."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for flag in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage",
                 "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                 f"--window-size={width},{height}"):
        options.add_argument(flag)
    return webdriver.Chrome(options=options, service=Service(CHROMEDRIVER))


#: The viewport's canvas reduced to 64 x 64, as a flat list of RGB values.
_READ_THUMBNAIL = """
const canvas = [...document.querySelectorAll('canvas')]
    .sort((a, b) => b.width * b.height - a.width * a.height)[0];
if (!canvas || canvas.width === 0) return null;
const copy = document.createElement('canvas');
copy.width = 64; copy.height = 64;
const context = copy.getContext('2d');
context.drawImage(canvas, 0, 0, 64, 64);
return Array.from(context.getImageData(0, 0, 64, 64).data).filter((v, i) => i % 4 !== 3);
"""


def screenshot(driver):
    """(H, W, 3) uint8 array: the whole page as the browser shows it."""
    import io

    import numpy as np
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(driver.get_screenshot_as_png())).convert("RGB"))


def thumbnail(driver):
    """(64, 64, 3) int array: the viewport shrunk, to compare whole frames; None before it
    draws."""
    import numpy as np

    values = driver.execute_script(_READ_THUMBNAIL)
    return None if values is None else np.array(values, int).reshape(64, 64, 3)


def pixel(driver, x: float = 0.5, y: float = 0.5) -> list[int] | None:
    """RGB (0..255) of the viewport at fractions ``x``, ``y`` of its width and height."""
    return driver.execute_script(_READ_PIXEL, x, y)


def wait_for(condition, timeout: float = 30.0, every: float = 0.05):
    """Poll ``condition()`` until it returns something truthy; that value, or None."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        value = condition()
        if value:
            return value
        time.sleep(every)
    return None


def colour_input(driver, label: str):
    """The text input of the colour picker labelled ``label``."""
    from selenium.webdriver.common.by import By

    return driver.find_element(
        By.XPATH, f"//*[normalize-space(text())='{label}']/following::input[1]")


def type_colour(driver, label: str, hex_code: str) -> None:
    """Type ``#rrggbb`` into the picker labelled ``label`` and press Enter, as a person would."""
    from selenium.webdriver.common.keys import Keys

    field = colour_input(driver, label)
    field.click()
    field.send_keys(Keys.CONTROL, "a")
    field.send_keys(hex_code, Keys.ENTER)


def close_to(a, b, tolerance: int) -> bool:
    return a is not None and max(abs(int(u) - int(v)) for u, v in zip(a, b)) <= tolerance


#: A watcher of the viewport's centre pixel, frame by frame: ``__studio.latency()`` is the
#: time from the last Enter key or pointer release (a click, the end of a drag) to the first
#: frame whose centre changed, in ms.
_WATCH = """
const canvas = [...document.querySelectorAll('canvas')]
    .sort((a, b) => b.width * b.height - a.width * a.height)[0];
const context = document.createElement('canvas').getContext('2d', {willReadFrequently: true});
const watch = {sent: null, changed: null, last: null};
watch.latency = () => watch.changed === null ? null : watch.changed - watch.sent;
document.addEventListener('keydown', event => {
    if (event.key === 'Enter') { watch.sent = performance.now(); watch.changed = null; }
}, true);
document.addEventListener('pointerup', () => {
    watch.sent = performance.now(); watch.changed = null;
}, true);
function poll() {
    context.drawImage(canvas, canvas.width >> 1, canvas.height >> 1, 1, 1, 0, 0, 1, 1);
    const now = Array.from(context.getImageData(0, 0, 1, 1).data.slice(0, 3));
    if (watch.sent !== null && watch.changed === null && watch.last !== null
        && now.reduce((sum, v, i) => sum + Math.abs(v - watch.last[i]), 0) > 30) {
        watch.changed = performance.now();
    }
    watch.last = now;
    requestAnimationFrame(poll);
}
requestAnimationFrame(poll);
window.__studio = watch;
"""


def watch_centre(driver) -> None:
    """Start timing palette changes in the page (``change_latency``)."""
    driver.execute_script(_WATCH)


def change_latency(driver, timeout: float = 10.0) -> float | None:
    """Milliseconds from the last Enter typed (or pointer released) to the viewport's centre
    changing."""
    return wait_for(lambda: driver.execute_script("return window.__studio.latency()"), timeout)


def viewport(driver):
    """The viewport's canvas element (the largest canvas)."""
    from selenium.webdriver.common.by import By

    return max(driver.find_elements(By.TAG_NAME, "canvas"),
               key=lambda c: c.size["width"] * c.size["height"])


def drag(driver, start: tuple[float, float], end: tuple[float, float], steps: int = 10) -> None:
    """Drag the mouse across the viewport between fractions of its width and height."""
    from selenium.webdriver.common.action_chains import ActionChains

    canvas = viewport(driver)
    w, h = canvas.size["width"], canvas.size["height"]
    actions = ActionChains(driver).move_to_element_with_offset(
        canvas, round((start[0] - 0.5) * w), round((start[1] - 0.5) * h)).click_and_hold()
    for _ in range(steps):
        actions.move_by_offset(round((end[0] - start[0]) * w / steps),
                               round((end[1] - start[1]) * h / steps))
    actions.release().perform()


def click(driver, x: float = 0.5, y: float = 0.5) -> None:
    """Click the viewport at fractions ``x``, ``y`` of its width and height."""
    from selenium.webdriver.common.action_chains import ActionChains

    canvas = viewport(driver)
    w, h = canvas.size["width"], canvas.size["height"]
    ActionChains(driver).move_to_element_with_offset(
        canvas, round((x - 0.5) * w), round((y - 0.5) * h)).click().perform()
