"""Start-up check of the GUI: the system libraries Qt's X11 (xcb) platform plugin loads.

Without them Qt aborts the process ("could not load the Qt platform plugin
xcb").  :func:`missing_packages` tries each library by its soname (what the
plugin's loader does) and names the Debian/Ubuntu package that provides it.
No Qt import here.
"""
from __future__ import annotations

import ctypes
import os
import sys

# soname -> Debian/Ubuntu package (the libraries the PySide6 xcb plugin needs beyond libxcb itself)
XCB_LIBRARIES = {
    "libxcb-cursor.so.0": "libxcb-cursor0",
    "libxcb-icccm.so.4": "libxcb-icccm4",
    "libxcb-keysyms.so.1": "libxcb-keysyms1",
    "libxcb-image.so.0": "libxcb-image0",
    "libxcb-render-util.so.0": "libxcb-render-util0",
    "libxcb-shape.so.0": "libxcb-shape0",
    "libxcb-randr.so.0": "libxcb-randr0",
    "libxcb-xkb.so.1": "libxcb-xkb1",
    "libxkbcommon-x11.so.0": "libxkbcommon-x11-0",
    "libX11-xcb.so.1": "libx11-xcb1",
    "libEGL.so.1": "libegl1",
    "libfontconfig.so.1": "libfontconfig1",
}


def uses_xcb(environ=None, platform: str | None = None) -> bool:
    """True when Qt will pick its X11 (xcb) platform plugin: Linux, a DISPLAY, no Wayland, no other
    QT_QPA_PLATFORM."""
    env = os.environ if environ is None else environ
    platform = sys.platform if platform is None else platform
    qpa = env.get("QT_QPA_PLATFORM", "")
    if not platform.startswith("linux"):
        return False
    if qpa:
        return qpa.split(":")[0] == "xcb"
    return bool(env.get("DISPLAY")) and not env.get("WAYLAND_DISPLAY")


def missing_packages(libraries: dict | None = None) -> list[str]:
    """The packages whose library cannot be loaded ([] when all load)."""
    missing = []
    for soname, package in (XCB_LIBRARIES if libraries is None else libraries).items():
        try:
            ctypes.CDLL(soname)
        except OSError:
            missing.append(package)
    return missing


def problem(libraries: dict | None = None, environ=None) -> str | None:
    """One line naming the packages to install, or None when the GUI can start."""
    if not uses_xcb(environ):
        return None
    missing = missing_packages(libraries)
    if not missing:
        return None
    return (f"Qt's X11 platform plugin needs system libraries that are missing; on Debian/Ubuntu: "
            f"sudo apt-get install {' '.join(missing)} (or run with QT_QPA_PLATFORM=offscreen)")
