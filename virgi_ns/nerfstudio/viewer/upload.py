"""The viewer's file upload element (over viser's upload button) and the decoding of an uploaded
image."""

from __future__ import annotations

import io
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, Optional

import numpy as np
from nerfstudio.viewer.viewer_elements import ViewerElement

from virgi_ns.errors import InputError

if TYPE_CHECKING:
    from viser import ViserServer

MAX_UPLOAD_BYTES = 64 << 20


@dataclass
class Upload:
    """An uploaded file: its name and bytes."""

    name: str
    content: bytes


class ViewerUpload(ViewerElement[Optional[Upload]]):
    """A file upload button (viser's ``add_upload_button``); ``cb_hook(element)`` runs after each
    upload, with the file in ``element.value``."""

    def __init__(self, name: str, cb_hook: Callable[["ViewerUpload"], Any] = lambda element: None,
                 mime_type: str = "*/*", hint: Optional[str] = None, disabled: bool = False,
                 visible: bool = True) -> None:
        super().__init__(name, disabled=disabled, visible=visible, cb_hook=cb_hook)
        self.mime_type = mime_type
        self.hint = hint
        self._value: Optional[Upload] = None

    def _create_gui_handle(self, viser_server: "ViserServer") -> None:
        import viser

        self.gui_handle = viser_server.gui.add_upload_button(  # type: ignore[assignment]
            self.name, disabled=self.disabled, visible=self.visible, hint=self.hint, mime_type=self.mime_type,
            icon=viser.Icon.UPLOAD)

    def install(self, viser_server: "ViserServer") -> None:
        self._create_gui_handle(viser_server)
        assert self.gui_handle is not None

        def on_upload(event) -> None:
            f = event.target.value
            self._value = Upload(str(f.name), bytes(f.content))
            self.cb_hook(self)

        self.gui_handle.on_upload(on_upload)  # type: ignore[union-attr]

    @property
    def value(self) -> Optional[Upload]:
        return self._value

    @value.setter
    def value(self, value: Optional[Upload]) -> None:
        self._value = value


def decode_image(name: str, content: bytes) -> np.ndarray:
    """[H,W,3] float32 in [0,1] of an uploaded image; anything else is an :class:`InputError`."""
    from PIL import Image, UnidentifiedImageError

    if not content:
        raise InputError(f"{name or 'the upload'} is empty")
    if len(content) > MAX_UPLOAD_BYTES:
        raise InputError(f"{name} is larger than {MAX_UPLOAD_BYTES >> 20} MiB")
    try:
        with Image.open(io.BytesIO(content)) as im:
            im.load()
            if im.mode in ("RGBA", "LA", "PA") or (im.mode == "P" and "transparency" in im.info):
                im = im.convert("RGBA")
                rgb = np.asarray(im, dtype=np.float32)[..., :3] / 255.0
            else:
                rgb = np.asarray(im.convert("RGB"), dtype=np.float32) / 255.0
    except (UnidentifiedImageError, OSError, ValueError, Image.DecompressionBombError):
        raise InputError(f"{name or 'the upload'} is not an image (PNG, JPEG, ...)") from None
    return rgb


__all__ = ["MAX_UPLOAD_BYTES", "Upload", "ViewerUpload", "decode_image"]
