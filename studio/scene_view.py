"""Scene mode of the page (``app.ModeView``). The browser draws the run's splats itself
(``nerf_stage.splats``), each tab its own: a palette edit sends the splats' new colours, and
so does a camera move when the splats' weights depend on the view (a splat run's residual,
evaluated for the tab's camera: what the browser shows is what ``nerf-stage render`` makes
from there). Or every tab's viewport renders the weight NeRF from its own
camera, coarse while it moves and at the training resolution once it stops, and recolours
the cached weights on palette edits without the network; with splats, *full-quality still*
renders the network's view once. A box region, placed with a gizmo and sized in the panel,
keeps the edit inside it; moving it recolours without the network too
(``nerf_stage.edit.regions``)."""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

import numpy as np

from nerf_stage.edit.regions import Region

from .pictures import bounded_aspect, camera_pose, to_bytes
from .scene import MAX_TURNTABLE, SceneTarget, recoloured

PREVIEW_ROWS = 24  # rows of a scene view while the camera moves
SPLATS, NETWORK = "splats (in the browser)", "network (on the server)"
SETTLE_S = 0.15  # the camera has stopped when it has not moved for this long


class SceneView:
    """A trained run on the page of ``studio`` (an ``app.Studio``), one ``Viewport`` a tab."""

    export_label, export_button = "turntable GIF, or splats PLY or SPZ", "export"

    def __init__(self, studio, target: SceneTarget):
        self.studio, self.target = studio, target
        self.viewports: dict[int, Viewport] = {}

    def default_palette_path(self) -> Path:
        return self.target.default_palette()

    def build_panel(self, gui) -> None:
        """What draws the view (splats or the network) and the full-quality still; the
        region: on or off, and its size; its gizmo moves it in the scene."""
        splats = self.target.splats
        with gui.add_folder("View"):
            network = self.target.run is not None
            self.drawer = gui.add_dropdown(
                "drawn by", ((SPLATS,) if splats is not None else ()) + (
                    (NETWORK,) if network else ()),
                hint="splats: camera moves need no server; the network: full quality")
            self.drawer.on_update(lambda event: self._drawer_changed())
            still = gui.add_button("full-quality still", disabled=splats is None or not network,
                                   hint="the network's render of this view, until it moves")
            still.on_click(lambda event: self.viewports[event.client.client_id].still())
        self.covariances = None if splats is None else splats.covariances()
        self.studio.server.scene.set_up_direction(tuple(self.target.up))
        size = np.ptp(self.target.bounds, 0) / 4
        with gui.add_folder("Region"):
            self.local = gui.add_checkbox(
                "edit inside the box", initial_value=False,
                hint="the palette edit applies inside the box only; drag its gizmo to move it")
            self.size = gui.add_vector3("box size", initial_value=tuple(size.round(3)),
                                        min=(1e-3,) * 3, step=0.01)
        scene = self.studio.server.scene
        self.gizmo = scene.add_transform_controls(
            "/region", scale=float(size.max()), disable_rotations=True,
            position=tuple(self.target.centre), visible=False)
        self.box = scene.add_box("/region/box", color=(255, 204, 51), dimensions=tuple(size),
                                 wireframe=True, visible=False)
        for control in (self.local, self.size, self.gizmo):
            control.on_update(lambda event: self._region_changed())

    def region(self) -> Region | None:
        """The box the edit applies inside, when it is on."""
        if not self.local.value:
            return None
        size = np.maximum(np.asarray(self.size.value, np.float64), 1e-3)
        return Region("box", tuple(map(float, self.gizmo.position)), tuple((size / 2).tolist()))

    def saved_with_palette(self) -> dict:
        region = self.region()
        return {} if region is None else {"regions": [region.to_dict()]}

    def _region_changed(self) -> None:
        with self.studio.lock:
            self.gizmo.visible = self.box.visible = bool(self.local.value)
            self.box.dimensions = tuple(np.maximum(self.size.value, 1e-3))
            self.studio.redraw()

    def build_export_options(self, gui) -> None:
        self.turntable_views = gui.add_number("turntable views", initial_value=36, min=1,
                                              max=MAX_TURNTABLE, step=1)

    @property
    def splats_drawn(self) -> bool:
        return self.drawer.value == SPLATS

    def connect(self, client) -> None:
        look_from_home(client.camera, self.target)
        self.open_viewports()
        self.viewports[client.client_id] = Viewport(self.studio, self, client)

    def redraw(self) -> None:
        for viewport in self.open_viewports():
            viewport.recolour()

    def splat_colours(self, weights: np.ndarray | None = None) -> np.ndarray:
        """(S, 3) the splats' colours for the palette shown, of their (S, M) ``weights``
        (``Splats.colours``), inside the region only when it is on (a splat is in when its
        centre is)."""
        region = None if self.studio.before.value else self.region()
        return self.target.splats.colours(self.studio.shown_palette,
                                          [] if region is None else [region], weights)

    def _drawer_changed(self) -> None:
        with self.studio.lock:
            self.studio.redraw()
            for viewport in self.open_viewports():
                viewport.moved.set()  # the network draws from here (or no longer does)

    def export(self, client, path: str | os.PathLike, palette: np.ndarray,
               force: bool) -> list[Path]:
        viewport = self.viewports[client.client_id]
        region = self.region()
        return self.target.export(path, palette, camera_pose(client.camera),
                                  viewport.intrinsics(), int(self.turntable_views.value), force,
                                  [] if region is None else [region])

    def stop(self) -> None:
        for viewport in list(self.viewports.values()):
            viewport.stop()

    def open_viewports(self) -> list[Viewport]:
        """The viewports of the tabs still open (those of closed tabs are stopped, dropped)."""
        open_tabs = self.studio.server.get_clients()
        for gone in [cid for cid in self.viewports if cid not in open_tabs]:
            self.viewports.pop(gone).stop()
        return list(self.viewports.values())


def look_from_home(camera, target: SceneTarget) -> None:
    """Put a tab's ``camera`` (viser's) exactly at ``target``'s home camera: its position,
    its direction, its field of view and its roll (the camera's own up; a training camera
    need not stand level)."""
    pose = target.home_pose()
    eye = pose[:3, 3]
    camera.fov = target.fov_y
    camera.up_direction = tuple(pose[:3, 1])
    camera.position = eye
    camera.look_at = eye - pose[:3, 2] * max(np.linalg.norm(target.centre - eye), 1e-3)


class Viewport:
    """One tab's view in scene mode: its splats, recoloured for its camera when their
    weights depend on the view; or the network's render on camera moves, low resolution
    while the camera moves and at the training resolution once it stops, recoloured
    without the network on palette changes."""

    def __init__(self, studio, view: SceneView, client):
        self.studio, self.view, self.target, self.client = studio, view, view.target, client
        splats = self.target.splats
        self.seen = (None, None)  # the camera position the splats' weights were seen from
        self.splat_node = None if splats is None else client.scene.add_gaussian_splats(
            "/splats", splats.centres, view.covariances,
            self.view.splat_colours(self.splat_weights()), splats.opacities[:, None],
            visible=view.splats_drawn)
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

    def splat_weights(self) -> np.ndarray:
        """(S, M) the splats' weights seen from the tab's camera (``Splats.view_weights``),
        kept until it moves: a palette edit only recolours them."""
        eye = np.asarray(self.client.camera.position, np.float64)
        if self.seen[0] is None or not np.array_equal(eye, self.seen[0]):
            self.seen = (eye, self.target.splats.view_weights(eye))
        return self.seen[1]

    def intrinsics(self, rows: int | None = None):
        return self.target.intrinsics(bounded_aspect(self.client.camera),
                                      rows or self.target.rows)

    def _loop(self) -> None:
        while self.running:
            self.moved.wait()
            self.moved.clear()
            if not self.running:
                return
            if self.view.splats_drawn:  # the browser draws; a still is gone once it moves
                if self.render is not None:
                    self.render = None
                    self.client.scene.set_background_image(None)
                if self.target.splats.residual is not None:
                    self.recolour()
                continue
            self._draw(PREVIEW_ROWS)
            if not self.moved.wait(SETTLE_S):
                self._draw(None)

    def still(self) -> None:
        """The network's render of this tab's view at the training resolution, over the
        splats until the camera moves."""
        self._draw(None)

    def _draw(self, rows: int | None) -> None:
        try:
            pose = camera_pose(self.client.camera)
            self.render = self.target.render(pose, self.intrinsics(rows))
        except Exception as exc:  # a tab that went away, or a render that failed
            self.studio.say(f"**error:** {exc}")
            return
        self.recolour()
        self.drawn = (self.render.weights.shape[1], time.perf_counter())

    def recolour(self) -> None:
        """The splats' colours for this camera and the palette shown, or the still or the
        network's view recoloured."""
        if self.splat_node is not None:
            self.splat_node.visible = self.view.splats_drawn
            if self.view.splats_drawn:
                self.splat_node.rgbs = self.view.splat_colours(self.splat_weights())
        if self.render is None:
            return
        region = None if self.studio.before.value else self.view.region()
        image = recoloured(self.render, self.studio.shown_palette,
                           [] if region is None else [region])[0]
        self.client.scene.set_background_image(to_bytes(image), format="png")
