"""Writers that build an MCAP under ``<path>.part`` and rename it only when it is complete.

A crash or an exception inside ``with`` never leaves a half file that looks whole.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from types import TracebackType
from typing import Any, BinaryIO, TypeVar

logger = logging.getLogger(__name__)

_W = TypeVar("_W", bound="AtomicMcapFile")


class AtomicMcapFile:
    """Base of the MCAP writers: owns the ``.part`` file, ``close`` (rename) and ``abort``.

    Subclasses call :meth:`_open_part` first, then set ``self._writer`` (any object with
    ``finish()``, e.g. an ``mcap`` or ``mcap_ros2`` writer) on the returned file.
    """

    path: Path
    part_path: Path
    _file: BinaryIO
    _writer: Any
    _closed: bool

    def _open_part(self, path: str | os.PathLike[str]) -> BinaryIO:
        self.path = Path(path)
        self.part_path = self.path.with_name(self.path.name + ".part")
        self._file = open(self.part_path, "wb")  # noqa: SIM115 - closed in close()/abort()
        self._closed = False
        return self._file

    def __enter__(self: _W) -> _W:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    def close(self) -> Path:
        """Finish the MCAP (summary, footer) and move it to its final path."""
        if not self._closed:
            try:
                self._writer.finish()
                self._file.close()
            except BaseException:
                self.abort()
                raise
            os.replace(self.part_path, self.path)
            self._closed = True
            logger.info("wrote %s", self.path)
        return self.path

    def abort(self) -> None:
        """Discard the partial file; nothing is written to the final path."""
        if not self._closed:
            self._closed = True
            self._file.close()
            self.part_path.unlink(missing_ok=True)
            logger.warning("discarded partial recording %s", self.part_path)
