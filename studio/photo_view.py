"""Photo mode of the page: the image on screen, letterboxed in every tab, a chooser and a
thumbnail strip with a button under each thumbnail, and local edits drawn on the image:
a box (drag), brush dabs (click) or the colour under the eyedropper (click), inside which
the palette edit applies (``app.ModeView``, ``drawing``)."""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from palette_core.basis import weights_to_rgb
from palette_core.errors import InputError
from palette_core.selection import Selection

from .drawing import Drawing
from .photos import THUMBNAIL_PIXELS, PhotoTarget
from .pictures import BACKDROP, bounded_aspect, letterbox

STRIP = 7  # thumbnails around the current photo
JPEG_QUALITY = 92
TOOLS = ("everywhere", "box", "brush", "eyedropper")  # where an edit applies


class PhotoView:
    """The images of a weight stack on the page of ``studio`` (an ``app.Studio``)."""

    export_label, export_button = "export folder", "export images"

    def __init__(self, studio, target: PhotoTarget):
        self.studio, self.target = studio, target
        self.image = 0  # the image on screen
        self.drawing = Drawing(target.size, len(target.names))
        self.last_selection_ms = float("nan")

    def default_palette_path(self) -> Path:
        return self.target.path.with_name(f"{self.target.path.stem}_edited.json")

    def build_panel(self, gui) -> None:
        names = self.target.names
        with gui.add_folder("Image"):
            self.chooser = gui.add_dropdown("image", names, initial_value=names[0])
            self.chooser.on_update(lambda event: self.show_image(names.index(event.target.value)))
            step = gui.add_button_group("step", ["previous", "next"])
            step.on_click(lambda event: self.show_image(
                (self.image + (1 if event.target.value == "next" else -1)) % len(names)))
            self.strip = gui.add_image(np.zeros((8, 8, 3), np.uint8), label="neighbours")
            self.strip_buttons = gui.add_button_group("open", self._strip_labels(),
                                                      hint="open an image of the strip")
            self.strip_buttons.on_click(
                lambda event: self.show_image(int(event.target.value.strip("[]")) - 1))
        with gui.add_folder("Local edit"):
            self.tool = gui.add_dropdown(
                "edit applies", TOOLS, initial_value=TOOLS[0],
                hint="box: drag over the image; brush: click to paint; eyedropper: click a "
                     "colour. The palette edit then applies inside the selection only")
            self.tool.on_update(lambda event: self._use_tool(event.target.value))
            self.radius = gui.add_slider("brush radius", min=1, max=200, step=1,
                                         initial_value=20, hint="image pixels")
            self.feather = gui.add_slider("feather", min=0, max=50, step=1, initial_value=2,
                                          hint="soft edge of boxes and dabs, image pixels")
            self.distance = gui.add_slider("colour distance", min=0.01, max=0.5, step=0.01,
                                           initial_value=0.1, hint="eyedropper: RGB distance")
            gui.add_button("clear selection").on_click(lambda event: self._selected(
                self.drawing.clear, "selection cleared: edits apply everywhere"))
            self.edits_path = gui.add_text("edit file",
                                           initial_value=str(self.default_edits_path()))
            gui.add_button("save edit").on_click(lambda event: self.studio._write(
                event.client, lambda force: self.drawing.save(
                    self.edits_path.value, self.target.stack, self.studio.editor.palette,
                    force)))

    def build_export_options(self, gui) -> None:
        """Nothing beyond the folder."""

    def connect(self, client) -> None:
        aspect = [bounded_aspect(client.camera)]

        def resized(camera) -> None:  # orbit drags change nothing; a new frame letterboxes
            if abs(bounded_aspect(camera) - aspect[0]) > 1e-3:
                aspect[0] = bounded_aspect(camera)
                self._show_photo(client)

        client.camera.on_update(resized)
        with self.studio.lock:
            self._show_photo(client)
            self._show_strip()

    def redraw(self) -> None:
        for client in self.studio.server.get_clients().values():
            self._show_photo(client)
        self._show_strip()

    def export(self, client, path: str | os.PathLike, palette: np.ndarray,
               force: bool) -> list[Path]:
        return self.target.export(path, palette, force, self.drawing)

    def saved_with_palette(self) -> dict:
        """The selection is saved apart (*save edit*)."""
        return {}

    def default_edits_path(self) -> Path:
        return self.target.path.with_name(f"{self.target.path.stem}_edit.json")

    # Local edits ----------------------------------------------------------------------

    def _use_tool(self, tool: str) -> None:
        """Listen to the pointer for ``tool``: drags for boxes (which then no longer turn
        the camera, which photo mode does not use), clicks for the brush and eyedropper."""
        scene = self.studio.server.scene
        scene.remove_rect_select_callback("all")  # photo mode registers no others
        scene.remove_click_callback("all")
        if tool == "box":
            scene.on_rect_select()(self._boxed)
        elif tool in ("brush", "eyedropper"):
            scene.on_click()(self._clicked)

    def _boxed(self, event) -> None:
        corners = np.array([self._image_point(event.client, p)
                            for p in (event.screen_min, event.screen_max)])
        self._selected(lambda: self.drawing.box(self.image, corners, self.feather.value),
                       "box selected: edits apply inside it")

    def _clicked(self, event) -> None:
        point = self._image_point(event.client, event.screen_pos)
        if self.tool.value == "brush":
            self._selected(lambda: self.drawing.dab(self.image, point, self.radius.value,
                                                    self.feather.value),
                           "painted: edits apply inside the brush strokes")
            return

        def pick() -> None:
            h, w = self.target.size(self.image)
            if not np.isfinite(point).all():
                raise InputError("a click's point must be finite")
            x, y = np.clip(point, 0, [w - 1, h - 1]).astype(int)
            weights = np.asarray(self.target.stack.weights[self.image][y, x], np.float64)
            stack = self.target.stack
            colour = weights_to_rgb(weights, stack.palette, stack.basis, stack.order)
            near = Selection(near=tuple(np.clip(colour, 0, 1).tolist()),
                             distance=float(self.distance.value))  # InputError for NaN
            self.drawing.clear()
            self.drawing.near = (np.asarray(near.near), near.distance)

        self._selected(pick, "colour picked: edits apply where the image is near it")

    def _selected(self, change, message: str) -> None:
        """Change the selection and redraw; ``last_selection_ms`` times both (the server's
        part of a stroke)."""
        with self.studio.lock:
            start = time.perf_counter()
            try:
                change()
            except InputError as exc:  # a message no page of ours sends
                self.studio.say(f"**error:** {exc}")
                return
            self.studio.redraw()
            self.last_selection_ms = 1000 * (time.perf_counter() - start)
            self.studio.say(message)

    def _drawing_shown(self) -> Drawing | None:
        """The selection, unless the page shows the original (before/after)."""
        return None if self.studio.before.value else self.drawing

    def _image_point(self, client, screen) -> np.ndarray:
        """(x, y) pixel of the image on screen (full size) under ``screen`` (fractions of the
        viewport, from its top left), through the letterbox."""
        h, w = self.target.weights(self.image).shape[:2]
        aspect = bounded_aspect(client.camera)
        width, height = max(w, round(h * aspect)), max(h, round(w / aspect))
        x = screen[0] * width - (width - w) // 2
        y = screen[1] * height - (height - h) // 2
        full_h, full_w = self.target.size(self.image)
        return np.array([x * full_w / w, y * full_h / h])

    def stop(self) -> None:
        """Nothing runs in the background."""

    def show_image(self, i: int) -> None:
        with self.studio.lock:
            self.image = i
            self.chooser.value = self.target.names[i]
            self.redraw()

    def _show_photo(self, client) -> None:
        image = self.target.view(self.image, self.studio.shown_palette,
                                 drawing=self._drawing_shown())
        client.scene.set_background_image(letterbox(image, bounded_aspect(client.camera)),
                                          format="jpeg", jpeg_quality=JPEG_QUALITY)

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

    def _show_strip(self) -> None:
        """Thumbnails of the images around the current one, the current one framed, and under
        them a button each that opens it (the current one marked)."""
        around = self._strip_images()
        thumbs = [self.target.view(i, self.studio.shown_palette, THUMBNAIL_PIXELS,
                                   self._drawing_shown()) for i in around]
        height = max(t.shape[0] for t in thumbs)
        tiles = []
        for i, thumb in zip(around, thumbs):
            tile = np.empty((height + 6, thumb.shape[1] + 6, 3), np.uint8)
            tile[:] = (255, 204, 51) if i == self.image else BACKDROP
            tile[3:3 + thumb.shape[0], 3:-3] = thumb
            tiles.append(tile)
        self.strip.image = np.concatenate(tiles, axis=1)
        self.strip_buttons.options = self._strip_labels()
