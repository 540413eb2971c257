"""Stages from photos to a textured mesh; each calls ``dvr/`` (never the reverse).

OpenCV is loaded first, on purpose: pycolmap 4.2's extension carries its own zlib and exports it, and when it is
the first of the two to load, OpenCV's PNG writer later frees memory of the wrong zlib and the process aborts
(``import pycolmap, cv2`` then ``cv2.imwrite("x.png", …)``; the other order is fine). This package loads pycolmap
only through :mod:`pipeline.colmaplib`, after this module, so after OpenCV; a script that imported pycolmap itself
before this package gets a one-line warning naming the fix.
"""

import sys as _sys

if "pycolmap" in _sys.modules and "cv2" not in _sys.modules:
    print("warning: pycolmap was imported before pipeline (or cv2); OpenCV may then abort writing a PNG — import "
          "pipeline or cv2 first", file=_sys.stderr)

import cv2 as _cv2  # noqa: E402,F401  (before any pycolmap of this package: above)
