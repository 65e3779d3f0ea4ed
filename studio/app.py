"""The studio's web page, on viser: a palette panel and a viewport.

One editing session is shared by every browser tab; each tab has its own
viewport (its own camera and aspect). The panel holds the status line, a colour
picker per palette colour, before/after, undo and reset, harmonisation
(``harmonize``), the mode's own controls, and the exports. What differs between a
weight stack and a trained run is a ``ModeView`` (``photo_view``, ``scene_view``).
Every write goes through the library's atomic writers; an output that exists is
replaced only after the user confirms it. Only the studio's own page, opened with the
launch's token, can connect (``guard``); viser's public share tunnel is switched off.
"""

from __future__ import annotations

import contextlib
import os
import socket
import sys
import threading
import time
from pathlib import Path
from typing import Protocol

import numpy as np
import viser

from harmonize import TEMPLATES
from harmonize.batch import BEST
from palette_core.errors import InputError, OutputExists

from .editor import PaletteEditor
from .guard import Guard, guarded_server, is_loopback, log
from .photo_view import PhotoView
from .photos import PhotoTarget
from .pictures import to_bytes
from .scene import SceneTarget
from .scene_view import SceneView
from .splat_file import SplatFileTarget

NOTICE_S = 5.0  # how long a notification stays


class ModeView(Protocol):
    """What the page needs from a mode (``PhotoView``, ``SceneView``)."""

    export_label: str
    export_button: str

    def default_palette_path(self) -> Path:
        """Where *save palette* writes unless the user types another path."""

    def build_panel(self, gui) -> None:
        """The mode's own folder of the panel (after harmonisation)."""

    def build_export_options(self, gui) -> None:
        """Options of the export, between its path and its button."""

    def saved_with_palette(self) -> dict:
        """What *save palette* writes beside the colours (scene mode: the region)."""

    def connect(self, client) -> None:
        """A new tab: set its camera and show it."""

    def redraw(self) -> None:
        """Show every tab with ``studio.shown_palette`` (no network in scene mode)."""

    def export(self, client, path: str | os.PathLike, palette: np.ndarray,
               force: bool) -> list[Path]:
        """Write what the export button writes; the paths written."""

    def stop(self) -> None:
        """Stop what runs in the background."""


def check_port(host: str, port: int) -> None:
    """InputError unless ``port`` on ``host`` is a port number that is free (viser would
    quietly take another)."""
    if not 0 <= port <= 65535:
        raise InputError(f"must be in [0, 65535], got {port}", "port")
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as probe:
        try:
            probe.bind((host, port))
        except OSError as exc:
            raise InputError(f"cannot listen on {host}:{port}: {exc.strerror}", "port") from None


def open_target(path: str, splats: bool = True):
    """A ``PhotoTarget`` for a weight stack, a ``SceneTarget`` for a run folder (baked into
    splats unless not ``splats``), a ``SplatFileTarget`` for a splat file or splat stack.

    Raises
    ------
    InputError
        If ``path`` is neither.
    """
    from nerf_stage.train.checkpoint import CHECKPOINT
    from splat_files import is_splat_file
    from splat_files.stack import is_splat_stack

    target = Path(path)
    if target.is_dir() and (target / CHECKPOINT).is_file():
        return SceneTarget.open(target, bake=splats)
    if is_splat_file(target) or is_splat_stack(target):
        return SplatFileTarget.open(target)
    if target.suffix in (".npz", ".zarr"):
        return PhotoTarget.open(target)
    if not target.exists():
        raise InputError(f"{path} does not exist")
    raise InputError(f"{path} is neither a weight stack (.npz, .zarr), a splat file (.ply, "
                     f".spz, .splat, .sog) nor a run folder (a folder with {CHECKPOINT})")


def _no_share_url(*args, **kwargs) -> None:
    """Stands in for viser's ``request_share_url``: a public tunnel would bypass the guard."""
    log("refused a request for a public share URL")


class Studio:
    """A running studio: ``Studio(target, host, port)`` serves until ``stop()``.

    Attributes
    ----------
    target : PhotoTarget or SceneTarget
    view : ModeView
        ``PhotoView`` for a stack, ``SceneView`` for a run.
    editor : PaletteEditor
    server : viser.ViserServer
    guard : guard.Guard
    port : int
    url : str
        The page's address with the launch's token: the only way in.
    """

    def __init__(self, target: PhotoTarget | SceneTarget | SplatFileTarget, host: str = "127.0.0.1",
                 port: int = 8080):
        check_port(host, port)
        self.target = target
        self.editor = PaletteEditor(target.palette, target.shares)
        self.lock = threading.RLock()
        self.view: ModeView = (PhotoView(self, target) if isinstance(target, PhotoTarget)
                               else SceneView(self, target))
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
        self.server.on_client_connect(self.view.connect)

    def stop(self) -> None:
        self.view.stop()
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
        self.view.build_panel(gui)
        with gui.add_folder("Save"):
            self.palette_path = gui.add_text("palette file",
                                             initial_value=str(self.view.default_palette_path()))
            self.save_button = gui.add_button("save palette")
            self.save_button.on_click(lambda event: self._write(
                event.client, lambda force: self.editor.save(
                    self.palette_path.value, force, self.view.saved_with_palette())))
            self.export_path = gui.add_text(self.view.export_label,
                                            initial_value=str(self.target.default_export()))
            self.view.build_export_options(gui)
            gui.add_button(self.view.export_button).on_click(lambda event: self._write(
                event.client, lambda force: self.view.export(
                    event.client, self.export_path.value, self.editor.palette, force)))

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
        try:
            self.view.redraw()
        except InputError as exc:  # a panel value no page of ours sends (a NaN box size)
            self.say(f"**error:** {exc}")
            return
        self.last_redraw_ms = 1000 * (time.perf_counter() - start)

    # Writing ------------------------------------------------------------------------

    def _write(self, client, write, force: bool = False) -> None:
        """Run ``write(force) -> [paths]``; if an output exists, ask the user in a window
        before running it again with ``force``."""
        self.status.content = "writing ..."  # the result is said: a notification then
        try:
            written = write(force)
        except OutputExists as exc:
            message = str(exc)
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
