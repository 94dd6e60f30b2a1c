"""Images uploaded from the page as hologram targets: size- and pixel-capped, kept in a private temporary folder.

The page never names a path: an upload gets a number, and `upload:<number>` is the only way to refer to it. The
folder is created at a console's first upload (mode 0700), its files are named by the console, and it is deleted when
the console stops.
"""

from __future__ import annotations

import shutil
import tempfile
import threading
from pathlib import Path

from benchctl.errors import BadValueError
from benchctl.images import ACCEPTED, header_size, image_format, read_image
from benchctl.limits import check_pixels

MAX_UPLOAD_BYTES = 32 * 1024 * 1024
MAX_UPLOAD_PIXELS = 40_000_000  # a 40 Mpx photo; the ROI it is resized to is far smaller
MAX_UPLOADS = 50  # per console start: the private folder holds at most 50 x 32 MB
_SUFFIXES = {"PNG": ".png", "JPEG": ".jpg", "BMP": ".bmp", "TIFF": ".tif", "WebP": ".webp"}


class Uploads:
    """The console's upload folder and the uploads in it, numbered from 1."""

    def __init__(self, max_bytes: int = MAX_UPLOAD_BYTES, max_pixels: int = MAX_UPLOAD_PIXELS) -> None:
        self._folder: Path | None = None
        self.max_bytes = max_bytes
        self.max_pixels = max_pixels
        self.names: dict[str, str] = {}  # id -> the name the browser gave (shown only, never used as a path)
        self._lock = threading.Lock()

    @property
    def folder(self) -> Path:
        """The private folder, created on first use (a console that is never sent an image leaves nothing behind)."""
        if self._folder is None:
            self._folder = Path(tempfile.mkdtemp(prefix="benchctl-console-uploads-"))  # mode 0700
        return self._folder

    def check_room(self) -> None:
        """BadValueError when the console holds MAX_UPLOADS uploads already."""
        if len(self.names) >= MAX_UPLOADS:
            raise BadValueError(f"the console keeps at most {MAX_UPLOADS} uploads; restart it for more")

    def add(self, data: bytes, name: str) -> str:
        """Check and keep one uploaded image; returns its id. BadValueError for too many bytes, pixels or uploads,
        or anything that is not an image."""
        self.check_room()
        if len(data) > self.max_bytes:
            raise BadValueError(f"upload {name!r}: {len(data):,} bytes is above the limit of {self.max_bytes:,}")
        kind = image_format(data)
        if kind is None:
            raise BadValueError(f"upload {name!r}: not a {ACCEPTED} image")
        size = header_size(data)
        if size is None:
            raise BadValueError(f"upload {name!r}: a {kind} file whose header gives no image size; not decoded")
        self._check_pixels(name, *size)  # the console's own limit, before anything is decoded
        with self._lock:
            self.check_room()
            upload_id = str(len(self.names) + 1)
            path = self.folder / f"upload-{upload_id}{_SUFFIXES[kind]}"
            path.write_bytes(data)
            try:
                read_image(path)  # the project's limit, and an image OpenCV decodes
            except Exception:
                path.unlink(missing_ok=True)
                raise
            self.names[upload_id] = name[:200]
        return upload_id

    def _check_pixels(self, name: str, height: int, width: int) -> None:
        if height * width > self.max_pixels:
            raise BadValueError(f"upload {name!r}: {height} x {width} pixels is above the console's limit of "
                                f"{self.max_pixels:,}")
        check_pixels(f"upload {name!r}", height, width)

    def path(self, upload_id: str) -> Path:
        """The file of upload `upload_id`; BadValueError for an id the console did not give."""
        with self._lock:
            if upload_id not in self.names:
                raise BadValueError(f"no upload {upload_id!r} (uploads: {', '.join(self.names) or 'none'})")
            return next(self.folder.glob(f"upload-{upload_id}.*"))

    def remove_all(self) -> None:
        """Delete the folder and everything in it."""
        if self._folder is not None:
            shutil.rmtree(self._folder, ignore_errors=True)
