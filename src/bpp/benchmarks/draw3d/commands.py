"""``bpp draw3d calibration``: a lab's camera calibration checked against touched markers (``bpp draw3d generate`` is
generic)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from bpp.benchmarks.draw3d.calibration import CameraCalibration, check_calibration, read_touched, simulated_lab
from bpp.errors import UserError, require_extra


@dataclass(frozen=True)
class Draw3DCalibration:
    """Check a camera calibration (intrinsics and camera-to-robot extrinsic): the canvas pose a photo gives through
    it against the four red markers' centres touched with the pen tip (base frame, metres).

    With --simulate FOLDER, the simulator stands in for a lab: it writes the scene camera's calibration, a photo of a
    canvas at a random placement and the touched points into FOLDER, then checks them. The file formats are in
    docs/draw3d.md.

    Examples:
      bpp draw3d calibration --calibration lab/camera.json --photo lab/board.png --touched lab/touched.json
      bpp draw3d calibration --simulate calibration-example/
    """

    calibration: Path | None = None
    """The camera's calibration file (JSON)."""
    photo: Path | None = None
    """A photo of the board taken by that camera, the canvas's four markers visible."""
    touched: Path | None = None
    """The markers' centres touched with the pen tip: {"touched": [[x, y, z] x 4]} (top-left, top-right,
    bottom-right, bottom-left of the canvas upright)."""
    simulate: Path | None = None
    """Write a simulated lab's three files into this folder and check them."""
    seed: int = 0
    """The simulated canvas placement."""
    tolerance_mm: float = 5.0
    """A touched marker farther than this from the photo's fails the check."""


def draw3d_calibration(args: Draw3DCalibration) -> None:
    # imageio: for video and GIF files only
    import imageio.v3 as iio

    require_extra("cv2", "iphumi")
    if args.simulate is not None:
        paths = simulated_lab(args.simulate, args.seed)
        print("wrote " + ", ".join(str(p) for p in paths.values()))
        calibration, photo, touched = paths["calibration"], paths["photo"], paths["touched"]
    elif None in (args.calibration, args.photo, args.touched):
        raise UserError("give --calibration, --photo and --touched (or --simulate FOLDER)")
    else:
        calibration, photo, touched = args.calibration, args.photo, args.touched
    try:
        image = iio.imread(photo)
    except (OSError, ValueError) as err:
        raise UserError(f"{photo}: cannot read the photo ({err})") from None
    camera, points = CameraCalibration.load(calibration), read_touched(touched)
    try:
        check = check_calibration(camera, image[..., :3], points, args.tolerance_mm)
    except UserError as err:  # the inputs are checked: what is left is the photo's (its size, its markers)
        raise UserError(f"{photo}: {err}") from None
    print(check.report())
    if not check.passed:
        raise UserError(f"{calibration}: the calibration does not agree with the touched markers")


COMMANDS = {"calibration": (Draw3DCalibration, draw3d_calibration)}
