"""palette-studio in a real browser: a colour typed into the panel recolours the viewport.

Headless Chromium from Debian's packages (tests/browser.py); skipped, with the reason,
where it is not installed.
"""

import time

import numpy as np
import pytest

pytest.importorskip("viser")
pytest.importorskip("selenium")

from palette_core.stack import WeightStack, write_stack  # noqa: E402
from studio.app import Studio  # noqa: E402
from studio.photos import PhotoTarget  # noqa: E402
from studio.pictures import to_bytes  # noqa: E402

from . import browser  # noqa: E402

pytestmark = pytest.mark.skipif(not (browser.CHROMIUM and browser.CHROMEDRIVER),
                                reason=browser.MISSING)

PALETTE = np.array([[0.9, 0.1, 0.1], [0.1, 0.8, 0.2], [0.1, 0.2, 0.9]])
TOLERANCE = 12  # JPEG transport and texture filtering, in 0..255 levels


@pytest.fixture(scope="module")
def driver():
    chrome = browser.chromium()
    yield chrome
    chrome.quit()


@pytest.fixture
def serve():
    started = []

    def start(target):
        started.append(Studio(target, port=0))
        return started[-1]

    yield start
    for studio in started:
        studio.stop()


@pytest.fixture
def stripes(tmp_path):
    """A stack of one 60 x 30 image of three stripes, one palette colour each."""
    weights = np.zeros((30, 60, 3), np.float32)
    for j in range(3):
        weights[:, 20 * j:20 * (j + 1), j] = 1
    write_stack(WeightStack(PALETTE, [weights], ["stripes.png"], "mvc"), tmp_path / "w.npz")
    return PhotoTarget.open(tmp_path / "w.npz")


def test_photo_mode_recolours_live(driver, serve, stripes):
    """Three stripes, one palette colour each: typing a new colour 2 recolours the middle."""
    studio = serve(stripes)
    driver.get(studio.url)
    middle = to_bytes(PALETTE[1])
    assert browser.wait_for(lambda: browser.close_to(browser.pixel(driver), middle, TOLERANCE))
    browser.type_colour(driver, "colour 2", "#ff00ff")
    assert browser.wait_for(lambda: browser.close_to(browser.pixel(driver), (255, 0, 255),
                                                     TOLERANCE), timeout=10)
    assert studio.editor.palette[1].tolist() == [1, 0, 1]
    left = to_bytes(PALETTE[0])  # the other stripes keep their colours
    assert browser.close_to(browser.pixel(driver, 0.05), left, TOLERANCE)


def test_a_box_dragged_over_a_photo_edits_inside_it_only(driver, serve, stripes, tmp_path):
    """The box tool: a drag over part of the left stripe; a new colour 1 shows inside the
    box, the rest of the stripe keeps its colour; the edit saves."""
    studio = serve(stripes)
    driver.get(studio.url)
    red = to_bytes(PALETTE[0])
    assert browser.wait_for(lambda: browser.close_to(browser.pixel(driver, 0.15, 0.4), red,
                                                     TOLERANCE))
    studio.view.tool.value = "box"
    time.sleep(1)  # the page learns that drags now select
    browser.drag(driver, (0.05, 0.3), (0.3, 0.5))
    assert browser.wait_for(lambda: studio.view.drawing.masks, timeout=10)
    browser.type_colour(driver, "colour 1", "#ff00ff")
    assert browser.wait_for(lambda: browser.close_to(browser.pixel(driver, 0.15, 0.4),
                                                     (255, 0, 255), TOLERANCE), timeout=10)
    assert browser.close_to(browser.pixel(driver, 0.15, 0.7), red, TOLERANCE)  # below the box
    assert browser.close_to(browser.pixel(driver, 0.5, 0.4), to_bytes(PALETTE[1]), TOLERANCE)
    mask = studio.view.drawing.masks[0]
    assert mask[:, 45:].max() == 0 and mask[:, :10].max() == 1
    written = studio.view.drawing.save(tmp_path / "edit.json", studio.target.stack,
                                       studio.editor.palette)
    assert [p.name for p in written] == ["edit.json", "edit.masks"]


def test_scene_mode_recolours_without_the_network(driver, serve, scene_run, monkeypatch):
    """A tiny weight NeRF: once the view is refined, a typed colour gives exactly the
    recolouring of the cached weights."""
    from studio.scene import SceneTarget

    studio = serve(SceneTarget.open(scene_run, bake=False))  # the network draws
    driver.get(studio.url)
    rows = studio.target.run.intrinsics.height

    def settled():
        """The refined view, once the camera has not moved for a second."""
        views = list(studio.view.viewports.values())
        render = views[0].render if views else None
        if render is None or render.weights.shape[1] != rows:
            return None
        time.sleep(1.0)
        return render if views[0].render is render else None

    render = browser.wait_for(settled)
    assert render is not None
    calls = []
    monkeypatch.setattr(studio.target.run, "render", lambda *a, **k: calls.append(a))
    h, w = render.weights.shape[1:3]
    centre = np.s_[h // 2 - 1:h // 2 + 1, w // 2 - 1:w // 2 + 1]
    dominant = int(np.argmax(render.weights[0][centre].sum((0, 1))[:len(studio.editor.palette)]))
    new = to_bytes(1 - studio.editor.palette[dominant])
    browser.type_colour(driver, f"colour {dominant + 1}", "#{:02x}{:02x}{:02x}".format(*new))
    assert browser.wait_for(lambda: np.array_equal(to_bytes(studio.editor.palette[dominant]), new))
    block = to_bytes(render.recolor(studio.editor.palette)[0][centre]).reshape(-1, 3)
    low, high = block.min(0).astype(int) - 3, block.max(0).astype(int) + 3

    def shows_the_recolouring():
        got = browser.pixel(driver)
        return got is not None and all(lo <= g <= hi for g, lo, hi in zip(got, low, high))

    assert browser.wait_for(shows_the_recolouring, timeout=10), (browser.pixel(driver), low, high)
    assert not calls  # recoloured from the cached weights

    # a region far from everything keeps the edit out of the view; one around the scene
    # lets it in again; neither runs the network
    view = studio.view
    def unobstructed():  # the gizmo sits over the pixel read
        view.gizmo.visible = view.box.visible = False
        return shows_the_recolouring()

    view.gizmo.position = tuple(studio.target.centre + 100.0)  # as a drag of the gizmo would
    view.size.value = (0.01, 0.01, 0.01)
    view.local.value = True
    original = to_bytes(render.recolor()[0][centre]).reshape(-1, 3)
    low, high = original.min(0).astype(int) - 3, original.max(0).astype(int) + 3
    assert browser.wait_for(unobstructed, timeout=10), (browser.pixel(driver), low, high)
    view.gizmo.position = tuple(studio.target.centre)
    view.size.value = tuple(np.ptp(studio.target.bounds, 0) * 4)
    low, high = block.min(0).astype(int) - 3, block.max(0).astype(int) + 3
    assert browser.wait_for(unobstructed, timeout=10), (browser.pixel(driver), low, high)
    assert not calls
    assert view.saved_with_palette()["regions"][0]["shape"] == "box"


def test_scene_mode_splats_are_drawn_by_the_browser(driver, serve, scene_run, monkeypatch):
    """The browser draws the splats: a camera move gives new frames and a palette edit new
    colours, and the network never runs. Splats whose weights depend on the view are
    recoloured for the tab's camera when it moves."""
    from nerf_stage.splats import Splats
    from studio.scene import SceneTarget

    target = SceneTarget.open(scene_run, bake=False)
    rng = np.random.default_rng(0)  # opaque splats around the scene's middle
    n, k = 400, len(target.palette)
    spread = np.ptp(target.bounds, 0) / 6
    target.splats = Splats(
        (target.centre + rng.normal(size=(n, 3)) * spread).astype(np.float32),
        np.tile(spread / 4, (n, 1)).astype(np.float32), np.tile([1, 0, 0, 0], (n, 1)).astype(
            np.float32), np.full(n, 0.9, np.float32), np.eye(k, dtype=np.float32)[
            rng.integers(k, size=n)], target.palette, target.run.basis, target.run.order,
        np.ones(3), {})
    residual = rng.normal(size=(n, 3, k)).astype(np.float32)
    target.splats.residual = residual - residual.mean(2, keepdims=True)
    calls = []
    monkeypatch.setattr(target.run, "render", lambda *a, **k: calls.append(a))
    studio = serve(target)
    driver.get(studio.url)
    first = browser.wait_for(lambda: _settled_frame(driver), timeout=60)
    assert first is not None
    first = first[0]
    studio._apply(lambda: [studio.editor.set_colour(i, np.array([1.0, 0.0, 1.0]))
                           for i in range(len(target.palette))])
    recoloured = browser.wait_for(lambda: _changed(driver, first), timeout=10)
    assert recoloured is not None
    recoloured = recoloured[0]
    client = next(iter(studio.server.get_clients().values()))
    with client.atomic():
        client.camera.position = client.camera.position + np.array([1.0, 0.5, 0.0])
    assert browser.wait_for(lambda: _changed(driver, recoloured), timeout=10) is not None
    studio._apply(lambda: [studio.editor.set_colour(i, c)
                           for i, c in enumerate(target.palette[::-1])])
    node = studio.view.viewports[client.client_id].splat_node
    for step in ([0.0, 0.0, 1.0], [-2.0, 0.0, 0.0]):
        with client.atomic():
            client.camera.position = client.camera.position + np.array(step)

        def for_this_camera():
            eye = np.asarray(client.camera.position)
            weights = target.splats.view_weights(eye)
            expected = np.round(target.splats.colours(target.palette[::-1], weights=weights)
                                * 255)
            return np.abs(node.rgbs.astype(float) - expected).max() <= 1

        assert browser.wait_for(for_this_camera, timeout=10)
    diffuse = np.round(target.splats.colours(target.palette[::-1]) * 255)
    assert np.abs(node.rgbs.astype(float) - diffuse).max() > 10  # not the diffuse colours
    assert not calls  # neither the edits nor the moves ran the network


def _settled_frame(driver):
    """The viewport (in a list: ``wait_for`` wants it truthy), once two reads a second apart
    agree."""
    before = browser.thumbnail(driver)
    time.sleep(1.0)
    after = browser.thumbnail(driver)
    return [after] if before is not None and np.array_equal(before, after) else None


def _changed(driver, frame):
    """The viewport (in a list), once it differs from ``frame`` in some pixels."""
    now = browser.thumbnail(driver)
    return [now] if now is not None and np.abs(now - frame).max() > 40 else None


@pytest.fixture
def attacker_site(tmp_path):
    """A web site on another port of this machine: ``publish(html) -> url``."""
    import functools
    import http.server
    import threading

    site = tmp_path / "site"
    site.mkdir()
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(site))
    handler.log_message = lambda *args: None
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()

    def publish(html: str) -> str:
        (site / "index.html").write_text(html)
        return f"http://127.0.0.1:{server.server_address[1]}/index.html"

    yield publish
    server.shutdown()


@pytest.mark.parametrize("guarded", [True, False], ids=["guarded", "unguarded-control"])
def test_a_page_from_another_origin_cannot_write_files(driver, serve, attacker_site, tmp_path,
                                                       monkeypatch, guarded):
    """A page of another site, open in the same browser, opens the studio's socket (even
    knowing the token), types a palette path and presses *save palette*. The studio refuses
    the socket and nothing is written; the control run without the guard shows that the same
    page would have written the file."""
    import json

    import msgspec
    import viser
    from viser._messages import ViewerCameraMessage

    from studio.guard import Guard

    if not guarded:
        monkeypatch.setattr(Guard, "refusal", lambda self, request, port: None)
    write_stack(WeightStack(PALETTE, [np.full((4, 4, 3), 1 / 3, np.float32)], ["a.png"]),
                tmp_path / "w.npz")
    studio = serve(PhotoTarget.open(tmp_path / "w.npz"))
    stolen = tmp_path / "planted" / "evil.json"
    camera = ViewerCameraMessage((1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 1.0, 0.01, 100.0, 400,
                                 600, (0.0, 0.0, 0.0), (0.0, 1.0, 0.0))
    messages = [msgspec.msgpack.encode(camera.as_serializable_dict())] + [
        msgspec.msgpack.encode({"type": "GuiUpdateMessage", "uuid": handle._impl.uuid,
                                "updates": {"value": value}})
        for handle, value in [(studio.palette_path, str(stolen)), (studio.save_button, True)]]
    url = attacker_site(f"""<script>
    window.result = "pending";
    const socket = new WebSocket("ws://127.0.0.1:{studio.port}/?token={studio.guard.token}",
                                 ["viser-v{viser.__version__}"]);
    socket.binaryType = "arraybuffer";
    socket.onopen = () => {{
        window.result = "open";
        for (const bytes of {json.dumps([list(m) for m in messages])})
            socket.send(new Uint8Array(bytes));
    }};
    socket.onclose = () => {{ if (window.result === "pending") window.result = "refused"; }};
    </script>""")
    driver.get(url)
    result = browser.wait_for(lambda: driver.execute_script(
        "return window.result === 'pending' ? null : window.result"), timeout=20)
    if guarded:
        assert result == "refused"
        time.sleep(1.0)  # what would have been written, given the time
        assert not stolen.exists() and studio.palette_path.value != str(stolen)
    else:
        assert result == "open"
        assert browser.wait_for(stolen.exists, timeout=20)


def test_the_home_view_is_exactly_a_training_camera_roll_included(driver, serve, scene_run):
    """A tab opens at the home camera as the browser reports it back, and stays there:
    position, direction and roll (a camera tilted 30 degrees about its axis stays
    tilted)."""
    from studio.pictures import camera_pose
    from studio.scene import SceneTarget

    target = SceneTarget.open(scene_run, bake=False)
    home = target.home_pose().copy()
    roll = np.radians(30)
    turn = np.array([[np.cos(roll), -np.sin(roll), 0], [np.sin(roll), np.cos(roll), 0],
                     [0, 0, 1]])
    home[:3, :3] = home[:3, :3] @ turn
    target.home = home
    studio = serve(target)
    driver.get(studio.url)
    assert browser.wait_for(lambda: studio.server.get_clients(), timeout=30)
    client = next(iter(studio.server.get_clients().values()))

    def arrived():
        pose = camera_pose(client.camera)
        return np.allclose(pose[:3, :3], home[:3, :3], atol=1e-3) and np.allclose(
            pose[:3, 3], home[:3, 3], atol=1e-3)

    assert browser.wait_for(arrived, timeout=30), (camera_pose(client.camera), home)
    time.sleep(1.5)  # and stays: the orbit's up, set later, once moved the camera
    assert arrived(), (camera_pose(client.camera), home)
