"""Photo mode of the page: the image on screen, letterboxed in every tab, a chooser and a
thumbnail strip with a button under each thumbnail (``app.ModeView``)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .photos import THUMBNAIL_PIXELS, PhotoTarget
from .pictures import BACKDROP, bounded_aspect, letterbox

STRIP = 7  # thumbnails around the current photo
JPEG_QUALITY = 92


class PhotoView:
    """The images of a weight stack on the page of ``studio`` (an ``app.Studio``)."""

    export_label, export_button = "export folder", "export images"

    def __init__(self, studio, target: PhotoTarget):
        self.studio, self.target = studio, target
        self.image = 0  # the image on screen

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
        return self.target.export(path, palette, force)

    def stop(self) -> None:
        """Nothing runs in the background."""

    def show_image(self, i: int) -> None:
        with self.studio.lock:
            self.image = i
            self.chooser.value = self.target.names[i]
            self.redraw()

    def _show_photo(self, client) -> None:
        image = self.target.view(self.image, self.studio.shown_palette)
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
        thumbs = [self.target.view(i, self.studio.shown_palette, THUMBNAIL_PIXELS)
                  for i in around]
        height = max(t.shape[0] for t in thumbs)
        tiles = []
        for i, thumb in zip(around, thumbs):
            tile = np.empty((height + 6, thumb.shape[1] + 6, 3), np.uint8)
            tile[:] = (255, 204, 51) if i == self.image else BACKDROP
            tile[3:3 + thumb.shape[0], 3:-3] = thumb
            tiles.append(tile)
        self.strip.image = np.concatenate(tiles, axis=1)
        self.strip_buttons.options = self._strip_labels()
