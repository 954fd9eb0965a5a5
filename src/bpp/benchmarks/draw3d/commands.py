"""``bpp draw3d calibration``: a lab's camera calibration checked against touched markers; ``bpp draw3d from-iphumi``:
drawings recorded with an iPhUMI phone as demonstrations (``bpp draw3d generate`` is generic)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import tyro

from bpp.benchmarks.draw3d.calibration import CameraCalibration, check_calibration, read_touched, simulated_lab
from bpp.benchmarks.draw3d.phone import START_HEIGHT, from_iphumi
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


@dataclass(frozen=True)
class Draw3DFromIphumi:
    """Turn drawings recorded with an iPhUMI phone on the marked canvas into demonstrations of this benchmark: the
    pen's poses in the canvas's frame, whether it inks, the ink so far, and a Goal-Image goal photo of the ink on the
    simulated board. The recordings are processed first with bpp iphumi process --canvas --fps 20. Merge the result
    with the scripted arm's (bpp store merge) to train on both, or evaluate with it to prompt with the phone's
    drawings (bpp eval RUN --tasks STORE); a policy trained on both observes with --obs canvas.

    Examples:
      bpp iphumi process exports/drawings --canvas --fps 20 --out data/iphumi/drawings.zarr
      bpp draw3d from-iphumi data/iphumi/drawings.zarr --out data/draw3d/phone.zarr
    """

    source: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="PROCESSED_STORE")] = Path()
    out: Path = Path("data/draw3d/phone.zarr")
    """Store to write (a .zarr folder)."""
    goal_size: int = 64
    """Side (px) of each demonstration's goal photo of the board (0: none)."""
    start_height: float = START_HEIGHT
    """Steps before the pen first comes this close to the canvas (m), the phone held up to look at it, are left out."""
    seed: int = 0
    """The goal photos' canvas placements."""
    overwrite: bool = False
    """Replace an existing store."""


def draw3d_from_iphumi(args: Draw3DFromIphumi) -> None:
    if str(args.source) in ("", "."):
        raise UserError("give the processed iPhUMI store (bpp iphumi process --canvas --fps 20 ... --out STORE)")
    store = from_iphumi(
        args.source,
        args.out,
        goal_size=args.goal_size,
        start_height=args.start_height,
        seed=args.seed,
        overwrite=args.overwrite,
    )
    print(f"[draw3d] {store.num_episodes} demonstrations of {store.num_tasks} drawings -> {args.out}")


COMMANDS = {
    "calibration": (Draw3DCalibration, draw3d_calibration),
    "from-iphumi": (Draw3DFromIphumi, draw3d_from_iphumi),
}
