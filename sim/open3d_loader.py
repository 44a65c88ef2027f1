"""Import open3d without a system libusb-1.0: preload the copy shipped by the libusb-package wheel."""

from __future__ import annotations

import ctypes
import functools
import importlib
import logging

from sim.errors import SimError

log = logging.getLogger(__name__)


@functools.cache
def open3d():
    """Return the imported ``open3d`` module (libusb preloaded if the system lacks it)."""
    try:
        return importlib.import_module("open3d")
    except ImportError as first:
        if "libusb" not in str(first):
            raise SimError(f"open3d cannot be imported: {first}") from first
    try:
        import libusb_package

        path = libusb_package.get_library_path()
        ctypes.CDLL(str(path), mode=ctypes.RTLD_GLOBAL)
        log.debug("preloaded libusb from %s", path)
        return importlib.import_module("open3d")
    except Exception as exc:  # noqa: BLE001 - report the root cause with a fix
        raise SimError(
            "open3d needs libusb-1.0: install the 'libusb-package' wheel or the system "
            f"library (apt-get install libusb-1.0-0); import failed with: {exc}"
        ) from exc
