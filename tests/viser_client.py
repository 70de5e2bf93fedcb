"""A stand-in for the browser in the viewer tests: a websocket client that speaks viser's protocol
(msgpack messages, viser 0.2.7) to a real server, as viser's web client does. It sends its camera,
clicks buttons, sets dropdowns, checkboxes, sliders and colours, uploads files and clicks in the scene;
it keeps what the server sends: the GUI (by id, with labels, containers and values), the rendered
frames, file downloads and whether scene clicks are enabled. No browser, no JavaScript: the server
and everything behind it run as in ``ns-viewer``."""

from __future__ import annotations

import io
import threading
import time
import uuid
from typing import Any, Callable, Optional

import msgspec
import numpy as np
from viser import _messages as msg
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect


class ViserClient:
    def __init__(self, port: int, host: str = "127.0.0.1") -> None:
        self._ws = connect(f"ws://{host}:{port}", max_size=None, open_timeout=30)
        self._cond = threading.Condition()
        self.gui: dict[str, dict[str, Any]] = {}  # id -> the component's properties
        self.frames: list[np.ndarray] = []  # rendered frames, [H,W,3] uint8, oldest first
        self.downloads: dict[str, bytes] = {}
        self._transfers: dict[str, dict] = {}
        self._acks: set[str] = set()
        self.pointer_enabled = False
        self.closed = False
        self._reader = threading.Thread(target=self._read, daemon=True, name="viser-test-client")
        self._reader.start()

    # ----------------------------------------------------------------------- receiving
    def _read(self) -> None:
        try:
            while True:
                raw = self._ws.recv()
                batch = msgspec.msgpack.decode(raw)
                with self._cond:
                    for m in batch if isinstance(batch, list) else [batch]:
                        self._handle(m)
                    self._cond.notify_all()
        except ConnectionClosed:
            pass
        finally:
            with self._cond:
                self.closed = True
                self._cond.notify_all()

    def _handle(self, m: dict) -> None:
        kind = m.get("type", "")
        if kind.startswith("GuiAdd"):
            self.gui[m["id"]] = {**m, "kind": kind}
        elif kind == "GuiUpdateMessage" and m["id"] in self.gui:
            self.gui[m["id"]].update(m["updates"])
        elif kind == "GuiRemoveMessage":
            self.gui.pop(m["id"], None)
        elif kind == "BackgroundImageMessage":
            from PIL import Image

            with Image.open(io.BytesIO(m["rgb_bytes"])) as im:
                self.frames.append(np.asarray(im.convert("RGB")).copy())
        elif kind == "ScenePointerEnableMessage" and m["event_type"] == "click":
            self.pointer_enabled = bool(m["enable"])
        elif kind == "FileTransferStart" and m.get("source_component_id") is None:
            self._transfers[m["transfer_uuid"]] = {"name": m["filename"], "count": m["part_count"], "parts": {}}
            self._finish_download(m["transfer_uuid"])
        elif kind == "FileTransferPart" and m["transfer_uuid"] in self._transfers:
            self._transfers[m["transfer_uuid"]]["parts"][m["part"]] = bytes(m["content"])
            self._finish_download(m["transfer_uuid"])
        elif kind == "FileTransferPartAck":
            self._acks.add(m["transfer_uuid"])

    def _finish_download(self, key: str) -> None:
        t = self._transfers[key]
        if len(t["parts"]) == t["count"]:
            self.downloads[t["name"]] = b"".join(t["parts"][i] for i in range(t["count"]))
            del self._transfers[key]

    def wait_for(self, what: Callable[[], Any], timeout: float = 60.0, message: str = "") -> Any:
        """Wait until ``what()`` (read under the client's lock) is truthy; returns it."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                got = what()
                if got:
                    return got
                left = deadline - time.monotonic()
                if left <= 0 or self.closed:
                    raise AssertionError(f"timed out waiting for {message or what}")
                self._cond.wait(left)

    # ---------------------------------------------------------------------- the GUI
    def find(self, label: str, inside: Optional[str] = None) -> str:
        """The id of the component labelled ``label`` (a folder's label too), within the folder
        labelled ``inside`` (at any depth) where given."""

        def within(cid: str, folder: str) -> bool:
            while cid in self.gui:
                if cid == folder:
                    return True
                cid = self.gui[cid].get("container_id", "")
            return cid == folder

        def search():
            folder = None
            if inside is not None:
                folders = [i for i, c in self.gui.items() if c["kind"] == "GuiAddFolderMessage" and c["label"] == inside]
                if len(folders) != 1:
                    return None
                folder = folders[0]
            hits = [i for i, c in self.gui.items() if c.get("label") == label
                    and (folder is None or within(c.get("container_id", ""), folder))]
            return hits[0] if len(hits) == 1 else None

        return self.wait_for(search, 60, f"one GUI component labelled {label!r}" + (f" in {inside!r}" if inside else ""))

    def value(self, cid: str) -> Any:
        with self._cond:
            return self.gui[cid].get("value")

    def text(self, cid: str) -> str:
        with self._cond:
            return self.gui[cid].get("markdown", "")

    def _send(self, message: msg.Message) -> None:
        self._ws.send(msgspec.msgpack.encode(message.as_serializable_dict()))

    def set(self, cid: str, value: Any) -> None:
        """Change a component's value as the browser does (a button click is ``set(id, True)``)."""
        self._send(msg.GuiUpdateMessage(cid, {"value": value}))

    def click(self, cid: str) -> None:
        self.set(cid, True)

    def upload(self, cid: str, name: str, content: bytes, mime_type: str = "image/png") -> None:
        """Upload a file through the upload button ``cid`` in one part, as the browser sends it."""
        for _ in range(3):
            key = uuid.uuid4().hex
            self._send(msg.FileTransferStart(cid, key, name, mime_type, 1, len(content)))
            time.sleep(0.2)  # viser handles messages on a thread pool: let the start land first
            self._send(msg.FileTransferPart(cid, key, 0, content))
            try:
                self.wait_for(lambda: key in self._acks, 10, f"the server's receipt of {name}")
                return
            except AssertionError:  # the part overtook the start and was dropped: send it again
                continue
        raise AssertionError(f"the server never acknowledged {name}")

    # ------------------------------------------------------------------- the camera
    def send_camera(self, c2w_opengl: np.ndarray, fov_y: float, aspect: float, scale: float = 10.0) -> None:
        """The browser's camera: ``c2w_opengl`` [3,4] (nerfstudio's axes and units), vertical field of
        view in radians; ``scale``: nerfstudio's viewer-to-scene scale (VISER_NERFSTUDIO_SCALE_RATIO)."""
        import viser.transforms as vtf

        R = np.asarray(c2w_opengl[:3, :3], dtype=np.float64) @ vtf.SO3.from_x_radians(np.pi).as_matrix()
        pos = np.asarray(c2w_opengl[:3, 3], dtype=np.float64) * scale
        wxyz = tuple(float(v) for v in vtf.SO3.from_matrix(R).wxyz)
        look = pos + R[:, 2]
        self._camera = (R, pos, fov_y, aspect)
        self._send(msg.ViewerCameraMessage(wxyz, tuple(map(float, pos)), float(fov_y), float(aspect),
                                           tuple(map(float, look)), tuple(float(v) for v in -R[:, 1])))

    def click_scene(self, u: float, v: float) -> None:
        """A click at (u, v) of the canvas (0..1 from the top left), with the ray the browser computes."""
        R, pos, fov_y, aspect = self._camera
        t = np.tan(fov_y / 2)
        d = R @ np.array([(2 * u - 1) * t * aspect, (2 * v - 1) * t, 1.0])
        d = d / np.linalg.norm(d)
        self._send(msg.ScenePointerMessage("click", tuple(map(float, pos)), tuple(map(float, d)), ((float(u), float(v)),)))

    # ---------------------------------------------------------------------- frames
    def frame_count(self) -> int:
        with self._cond:
            return len(self.frames)

    def wait_frame(self, where: Callable[[np.ndarray], bool], after: int = 0, timeout: float = 60.0,
                   message: str = "") -> np.ndarray:
        """The first frame after the ``after``-th for which ``where(frame)`` holds."""
        seen = [after]

        def find():
            for i in range(seen[0], len(self.frames)):
                if where(self.frames[i]):
                    return (self.frames[i],)
            seen[0] = len(self.frames)
            return None

        return self.wait_for(find, timeout, message or "a frame")[0]

    def close(self) -> None:
        self._ws.close()
        self._reader.join(10)
