"""The studio's web page, on viser: a palette panel and a viewport.

One editing session is shared by every browser tab; each tab has its own
viewport (its own camera and aspect). The panel holds the status line, a colour
picker per palette colour, before/after, undo and reset, harmonisation
(``harmonize``), the image or camera, and the exports. Every write goes through the
library's atomic writers; an output that exists is replaced only after the user
confirms it. Only the studio's own page, opened with the launch's token, can connect
(``guard``); viser's public share tunnel is switched off.
"""

from __future__ import annotations

import contextlib
import socket
import sys
import threading
import time
from pathlib import Path

import numpy as np
import viser
import viser.transforms as tf

from harmonize import TEMPLATES
from harmonize.batch import BEST
from palette_core.errors import InputError, OutputExists

from .editor import PaletteEditor
from .guard import Guard, guarded_server, is_loopback, log
from .photos import THUMBNAIL_PIXELS, PhotoTarget
from .scene import MAX_TURNTABLE, SceneTarget

BACKDROP = np.array([33, 33, 38], np.uint8)  # letterbox bars around a photo
STRIP = 7  # thumbnails around the current photo
PREVIEW_ROWS = 24  # rows of a scene view while the camera moves
SETTLE_S = 0.15  # the camera has stopped when it has not moved for this long
JPEG_QUALITY = 92
NOTICE_S = 5.0  # how long a notification stays
MAX_ASPECT = 8.0  # widest (and tallest) view drawn: a browser's aspect cannot size a render


def check_port(host: str, port: int) -> None:
    """InputError unless ``port`` on ``host`` is free (viser would quietly take another)."""
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as probe:
        try:
            probe.bind((host, port))
        except OSError as exc:
            raise InputError(f"cannot listen on {host}:{port}: {exc.strerror} "
                             "(choose another --port)") from None


def letterbox(image: np.ndarray, aspect: float) -> np.ndarray:
    """(H, W, 3) uint8 -> padded with ``BACKDROP`` to width / height = ``aspect``, centred."""
    h, w = image.shape[:2]
    width, height = max(w, round(h * aspect)), max(h, round(w / aspect))
    canvas = np.empty((height, width, 3), image.dtype)
    canvas[:] = BACKDROP
    top, left = (height - h) // 2, (width - w) // 2
    canvas[top:top + h, left:left + w] = image
    return canvas


def bounded_aspect(camera) -> float:
    """The browser's width / height, within [1 / MAX_ASPECT, MAX_ASPECT] (1 if not finite)."""
    aspect = float(camera.aspect)
    return float(np.clip(aspect, 1 / MAX_ASPECT, MAX_ASPECT)) if np.isfinite(aspect) else 1.0


def to_bytes(image: np.ndarray) -> np.ndarray:
    return np.round(np.clip(image, 0, 1) * 255).astype(np.uint8)


def camera_pose(camera) -> np.ndarray:
    """(4, 4) camera-to-world pose in our OpenGL convention from a viser camera (OpenCV
    axes: looks along +z, +y down)."""
    pose = np.eye(4)
    pose[:3, :3] = tf.SO3(np.asarray(camera.wxyz)).as_matrix() @ np.diag([1.0, -1.0, -1.0])
    pose[:3, 3] = camera.position
    return pose


def _no_share_url(*args, **kwargs) -> None:
    """Stands in for viser's ``request_share_url``: a public tunnel would bypass the guard."""
    log("refused a request for a public share URL")


class Studio:
    """A running studio: ``Studio(target, host, port)`` serves until ``stop()``.

    Attributes
    ----------
    target : PhotoTarget or SceneTarget
    editor : PaletteEditor
    server : viser.ViserServer
    guard : guard.Guard
    port : int
    url : str
        The page's address with the launch's token: the only way in.
    """

    def __init__(self, target: PhotoTarget | SceneTarget, host: str = "127.0.0.1",
                 port: int = 8080):
        check_port(host, port)
        self.target = target
        self.editor = PaletteEditor(target.palette, target.shares)
        self.lock = threading.RLock()
        self.image = 0  # photo mode: the image on screen
        self.views: dict[int, SceneView] = {}  # scene mode: per browser tab
        self.guard = Guard(host, f"{target.path.name} - palette-studio")
        with contextlib.redirect_stdout(sys.stderr), guarded_server(self.guard):
            # viser's banner goes to stderr: stdout is the URL's
            self.server = viser.ViserServer(host=host, port=port, label="palette-studio",
                                            verbose=False)
        self.server.request_share_url = _no_share_url
        self.port = self.server.get_port()
        shown = "127.0.0.1" if self.guard.wildcard else host
        shown = f"[{shown}]" if ":" in shown else shown
        self.url = f"http://{shown}:{self.port}/?token={self.guard.token}"
        if not is_loopback(host):
            log(f"warning: listening on {host}, not this machine only: anyone who can reach "
                "it and has the URL (its token) can edit and write files as you")
        self.server.gui.configure_theme(show_share_button=False, show_logo=False)
        self.server.gui.main_panel.dock_right()  # beside the picture, not over it
        self.server.scene.set_up_direction("+y")
        self.server.scene.world_axes.visible = False
        self.last_redraw_ms = float("nan")
        self._build_panel()
        self.server.on_client_connect(self._connect)

    def stop(self) -> None:
        for view in list(self.views.values()):
            view.stop()
        with contextlib.redirect_stdout(sys.stderr):
            self.server.stop()

    # The panel ------------------------------------------------------------------------

    def _build_panel(self) -> None:
        gui = self.server.gui
        self.status = gui.add_markdown(f"editing `{self.target.path.name}`: "
                                       f"{len(self.editor.palette)} colours")  # first: in sight
        with gui.add_folder("Palette"):
            self.pickers = []
            for i, colour in enumerate(self.editor.palette):
                picker = gui.add_rgb(f"colour {i + 1}",
                                     initial_value=tuple(to_bytes(colour).tolist()))
                picker.on_update(self._picked(i))
                self.pickers.append(picker)
            self.before = gui.add_checkbox("show original", initial_value=False,
                                           hint="before/after: the target's own palette")
            self.before.on_update(lambda event: self._apply(lambda: None))
            undo, reset = gui.add_button("undo"), gui.add_button("reset")
            undo.on_click(lambda event: self._apply(self._undo))
            reset.on_click(lambda event: self._apply(self.editor.reset))
        with gui.add_folder("Harmonise"):
            template = gui.add_dropdown("template", [BEST, *TEMPLATES], initial_value=BEST)
            strength = gui.add_slider("strength", min=0.0, max=1.0, step=0.05,
                                     initial_value=1.0)
            gui.add_button("harmonise").on_click(lambda event: self._apply(
                lambda: "harmonised with template **"
                        + self.editor.harmonize(template.value, strength.value) + "**"))
        if self.target.mode == "photos":
            self._build_photo_panel(gui)
        with gui.add_folder("Save"):
            self.palette_path = gui.add_text("palette file",
                                             initial_value=str(self._default_palette_path()))
            self.save_button = gui.add_button("save palette")
            self.save_button.on_click(lambda event: self._write(
                event.client, lambda force: self.editor.save(self.palette_path.value, force)))
            label = "export folder" if self.target.mode == "photos" else "turntable GIF"
            self.export_path = gui.add_text(label, initial_value=str(self.target.default_export()))
            if self.target.mode == "scene":
                self.turntable_views = gui.add_number("turntable views", initial_value=36, min=1,
                                                      max=MAX_TURNTABLE, step=1)
            button = "export images" if self.target.mode == "photos" else "export turntable"
            gui.add_button(button).on_click(lambda event: self._write(
                event.client, lambda force: self._export(event.client, force)))

    def _build_photo_panel(self, gui) -> None:
        names = self.target.names
        with gui.add_folder("Image"):
            self.chooser = gui.add_dropdown("image", names, initial_value=names[0])
            self.chooser.on_update(lambda event: self._show_image(names.index(event.target.value)))
            step = gui.add_button_group("step", ["previous", "next"])
            step.on_click(lambda event: self._show_image(
                (self.image + (1 if event.target.value == "next" else -1)) % len(names)))
            self.strip = gui.add_image(np.zeros((8, 8, 3), np.uint8), label="neighbours")
            self.strip_buttons = gui.add_button_group("open", self._strip_labels(),
                                                      hint="open an image of the strip")
            self.strip_buttons.on_click(
                lambda event: self._show_image(int(event.target.value.strip("[]")) - 1))

    def _strip_images(self) -> list[int]:
        """The images of the thumbnail strip: all of a short stack, else the current one in the
        middle of its neighbours."""
        n = len(self.target.names)
        if n <= STRIP:
            return list(range(n))
        return [(self.image + d) % n for d in range(-(STRIP // 2), STRIP // 2 + 1)]

    def _strip_labels(self) -> tuple[str, ...]:
        """Image numbers of the strip's buttons, the current one in brackets."""
        return tuple(f"[{i + 1}]" if i == self.image else str(i + 1)
                     for i in self._strip_images())

    def _default_palette_path(self) -> Path:
        path = self.target.path
        return (path / "edited_palette.json" if self.target.mode == "scene"
                else path.with_name(f"{path.stem}_edited.json"))

    # Edits --------------------------------------------------------------------------

    def _picked(self, i: int):
        def changed(event) -> None:
            if event.client is None:  # the server set it (undo, reset, harmonise)
                return
            if self.before.value:  # an edit shows the edited palette again
                self.before.value = False
            self._apply(lambda: self.editor.set_colour(i, np.array(event.target.value) / 255))
        return changed

    def _apply(self, edit) -> None:
        """Run an edit of the palette, then sync the pickers and redraw."""
        with self.lock:
            try:
                result = edit()
            except InputError as exc:
                self.say(f"**error:** {exc}")
                return
            for picker, colour in zip(self.pickers, self.shown_palette):
                picker.value = tuple(to_bytes(colour).tolist())
            self.redraw()
            if isinstance(result, str):
                self.say(result)

    def _undo(self) -> str:
        return "undone" if self.editor.undo() else "nothing to undo"

    @property
    def shown_palette(self) -> np.ndarray:
        return self.editor.original if self.before.value else self.editor.palette

    def say(self, text: str) -> None:
        """Show ``text`` (markdown) in the status line at the top of the panel, and as a
        notification in every tab, in sight wherever the panel is scrolled."""
        self.status.content = text
        plain = text.replace("**", "").replace("`", "")
        for client in self.server.get_clients().values():
            client.add_notification("palette-studio", plain, auto_close_seconds=NOTICE_S,
                                    color="red" if plain.startswith("error") else None)

    def redraw(self) -> None:
        """Recolour what every tab shows (no network run in scene mode)."""
        start = time.perf_counter()
        if self.target.mode == "photos":
            for client in self.server.get_clients().values():
                self._show_photo(client)
            self._show_strip()
        else:
            for view in self._scene_views():
                view.recolour()
        self.last_redraw_ms = 1000 * (time.perf_counter() - start)

    # Photo mode ---------------------------------------------------------------------

    def _show_image(self, i: int) -> None:
        with self.lock:
            self.image = i
            self.chooser.value = self.target.names[i]
            self.redraw()

    def _show_photo(self, client) -> None:
        image = self.target.view(self.image, self.shown_palette)
        client.scene.set_background_image(letterbox(image, bounded_aspect(client.camera)),
                                          format="jpeg", jpeg_quality=JPEG_QUALITY)

    def _show_strip(self) -> None:
        """Thumbnails of the images around the current one, the current one framed, and under
        them a button each that opens it (the current one marked)."""
        around = self._strip_images()
        thumbs = [self.target.view(i, self.shown_palette, THUMBNAIL_PIXELS) for i in around]
        height = max(t.shape[0] for t in thumbs)
        tiles = []
        for i, thumb in zip(around, thumbs):
            tile = np.empty((height + 6, thumb.shape[1] + 6, 3), np.uint8)
            tile[:] = (255, 204, 51) if i == self.image else BACKDROP
            tile[3:3 + thumb.shape[0], 3:-3] = thumb
            tiles.append(tile)
        self.strip.image = np.concatenate(tiles, axis=1)
        self.strip_buttons.options = self._strip_labels()

    # Scene mode ---------------------------------------------------------------------

    def _connect(self, client) -> None:
        if self.target.mode == "photos":
            aspect = [bounded_aspect(client.camera)]

            def resized(camera) -> None:  # orbit drags change nothing; a new frame letterboxes
                if abs(bounded_aspect(camera) - aspect[0]) > 1e-3:
                    aspect[0] = bounded_aspect(camera)
                    self._show_photo(client)

            client.camera.on_update(resized)
            with self.lock:
                self._show_photo(client)
                self._show_strip()
            return
        pose = self.target.home_pose()
        client.camera.fov = self.target.fov_y
        client.camera.up_direction = (0.0, 1.0, 0.0)
        client.camera.position = pose[:3, 3]
        client.camera.look_at = self.target.centre
        self._scene_views()
        self.views[client.client_id] = SceneView(self, client)

    def _scene_views(self) -> list[SceneView]:
        """The views of the tabs still open (those of closed tabs are stopped and dropped)."""
        open_tabs = self.server.get_clients()
        for gone in [cid for cid in self.views if cid not in open_tabs]:
            self.views.pop(gone).stop()
        return list(self.views.values())

    # Writing ------------------------------------------------------------------------

    def _export(self, client, force: bool) -> list[Path]:
        palette = self.editor.palette
        if self.target.mode == "photos":
            return self.target.export(self.export_path.value, palette, force)
        view = self.views[client.client_id]
        return self.target.export(self.export_path.value, palette, camera_pose(client.camera),
                                  view.intrinsics(), int(self.turntable_views.value), force)

    def _write(self, client, write, force: bool = False) -> None:
        """Run ``write(force) -> [paths]``; if an output exists, ask the user in a window
        before running it again with ``force``."""
        self.status.content = "writing ..."  # the result is said: a notification then
        try:
            written = write(force)
        except OutputExists as exc:
            message = str(exc).split(" (use")[0]  # the CLI's hint does not apply here
            self.say(f"{message}: replace?")
            self._confirm(client, message, lambda: self._write(client, write, force=True))
            return
        except (InputError, OSError) as exc:
            self.say(f"**error:** {exc}")
            return
        more = f" and {len(written) - 1} more" if len(written) > 1 else ""
        self.say(f"wrote `{written[0]}`{more}")

    def _confirm(self, client, message: str, replace) -> None:
        with client.gui.add_modal("Replace?") as modal:
            client.gui.add_markdown(f"{message}. Replace it?")
            yes, no = client.gui.add_button("replace"), client.gui.add_button("cancel")

            def confirmed(event) -> None:
                modal.close()
                replace()

            yes.on_click(confirmed)
            no.on_click(lambda event: modal.close())


class SceneView:
    """One tab's viewport in scene mode: renders on camera moves, low resolution while the
    camera moves and at the training resolution once it stops; recolours without the
    network on palette changes."""

    def __init__(self, studio: Studio, client):
        self.studio, self.client = studio, client
        self.render = None  # the WeightRender on screen
        self.drawn = (0, 0.0)  # rows of the last view drawn, and when (time.perf_counter)
        self.moved = threading.Event()
        self.running = True
        client.camera.on_update(lambda camera: self.moved.set())
        self.thread = threading.Thread(target=self._loop, daemon=True)
        self.thread.start()
        self.moved.set()

    def stop(self) -> None:
        self.running = False
        self.moved.set()

    def intrinsics(self, rows: int | None = None):
        target = self.studio.target
        return target.intrinsics(bounded_aspect(self.client.camera),
                                 rows or target.run.intrinsics.height)

    def _loop(self) -> None:
        while self.running:
            self.moved.wait()
            self.moved.clear()
            if not self.running:
                return
            self._draw(PREVIEW_ROWS)
            if not self.moved.wait(SETTLE_S):
                self._draw(None)

    def _draw(self, rows: int | None) -> None:
        try:
            pose = camera_pose(self.client.camera)
            self.render = self.studio.target.render(pose, self.intrinsics(rows))
        except Exception as exc:  # a tab that went away, or a render that failed
            self.studio.say(f"**error:** {exc}")
            return
        self.recolour()
        self.drawn = (self.render.weights.shape[1], time.perf_counter())

    def recolour(self) -> None:
        if self.render is None:
            return
        image = self.render.recolor(self.studio.shown_palette)[0]
        self.client.scene.set_background_image(to_bytes(image), format="png")
