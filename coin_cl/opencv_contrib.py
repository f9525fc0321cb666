"""The OpenCV contrib modules coin-cl calls, checked before a run starts.

coin-cl depends on `opencv-contrib-python-headless`. pip installs each OpenCV wheel into the same
`cv2` folder, so a plain `opencv-python(-headless)` installed beside it (by another package, or
earlier) can shadow the contrib build: `cv2` then lacks the modules below, and a run would stop
at the first call, after minutes of work. `require_contrib` says so at the start instead.
"""

from __future__ import annotations

# module -> what calls it
CONTRIB = {
    "xphoto": "the embedded inpainter's structure pass (FSR fill)",
    "quality": "the evaluation's GMSD",
}
FIX = (
    "pip uninstall -y opencv-python opencv-python-headless opencv-contrib-python "
    "opencv-contrib-python-headless && pip install opencv-contrib-python-headless"
)


def missing_contrib() -> list[str]:
    """The contrib modules of CONTRIB that the installed cv2 lacks."""
    import cv2

    return [m for m in CONTRIB if not hasattr(cv2, m)]


def require_contrib() -> None:
    """RuntimeError naming the missing modules, what uses them and the fix, if any is missing."""
    missing = missing_contrib()
    if missing:
        import cv2

        uses = "; ".join(f"cv2.{m}: {CONTRIB[m]}" for m in missing)
        raise RuntimeError(
            f"OpenCV {cv2.__version__} at {cv2.__file__} has no contrib modules ({uses}): a plain "
            f"OpenCV wheel shadows opencv-contrib-python-headless; reinstall it: {FIX}"
        )
