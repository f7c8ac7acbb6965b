#!/usr/bin/env python3
"""A screenshot of a run's live view (its `recording.rrd`) at a chosen tick, rendered headless.

The Rerun viewer has no command-line flag for the time cursor, and its time-panel blueprint has
no field for it (rerun 0.36.3), so the recording is cut at the tick instead: `rerun rrd split`
keeps the part before TICK + 1, its recording is copied without the sim's layout, and a
blueprint of our own shows it with the time panel following the newest data (so the cursor
stands on TICK), the World view zoomed to BOUNDS beside the edge-error curves, and the side
panels hidden. The headless viewer
writes the PNG; the notifications it pins to the top right (over the curves) are cropped off,
leaving the World view.

    scripts/view_screenshot.py RUN_DIR/recording.rrd --tick 46 --bounds 5 11 2.5 7.5 --out shot.png

TICK is the view's `tick` timeline (states logged by the view, counted from 1 over the whole
run); BOUNDS are world metres, x_min x_max y_min y_max (y up, as in the world). Needs the
`rerun` CLI (pip install rerun-sdk==0.36.3), Vulkan for the headless renderer (apt
mesa-vulkan-drivers) and Pillow.
"""

import argparse
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import rerun as rr
import rerun.blueprint as rrb
import rerun.experimental
from PIL import Image

APPLICATION_ID = "formation-control"
RECORDING_ID = "screenshot-"
#: The World view's share of the window's width (the curves take the rest).
WORLD_SHARE = 0.72


def blueprint(bounds):
    x0, x1, y0, y1 = bounds
    world = rrb.Spatial2DView(
        name="World",
        origin="world",
        # The view logs y flipped (Rerun's 2-D views are y-down).
        visual_bounds=rrb.VisualBounds2D(x_range=[x0, x1], y_range=[-y1, -y0]),
    )
    curves = rrb.TimeSeriesView(name="Edge errors (m)", origin="plots/formation/edge_error")
    return rrb.Blueprint(
        rrb.Horizontal(world, curves, column_shares=[WORLD_SHARE, 1.0 - WORLD_SHARE]),
        rrb.BlueprintPanel(state="hidden"),
        rrb.SelectionPanel(state="hidden"),
        rrb.TimePanel(state="collapsed", timeline="tick", play_state="following"),
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("recording", type=Path)
    parser.add_argument("--tick", type=int, required=True, help="the view's tick to show")
    parser.add_argument("--bounds", type=float, nargs=4, required=True, metavar=("X0", "X1", "Y0", "Y1"))
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--window-size", default="1280x800")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="view-screenshot-") as tmp:
        tmp = Path(tmp)
        subprocess.run(
            ["rerun", "rrd", "split", "--output-dir", str(tmp), "--timeline", "tick",
             "--time", str(args.tick + 1), "--recording-id", RECORDING_ID, str(args.recording)],
            check=True, capture_output=True,
        )
        # [-inf, tick + 1): the part whose name starts with the lowest tick, by number
        # (recording_1__11.rrd before recording_11__80.rrd, which a string sort inverts).
        before = min(tmp.glob("*.rrd"), key=lambda part: [int(x) for x in re.findall(r"\d+", part.stem)])
        # Its recording alone: the sim's own layout would compete with ours for the screen.
        reader = rr.experimental.RrdReader(before)
        data = tmp / "data.rrd"
        reader.stream(store=reader.recordings()[0]).write_rrd(
            data, application_id=APPLICATION_ID, recording_id=f"{RECORDING_ID}0"
        )
        layout = tmp / "blueprint.rrd"
        stream = rr.RecordingStream(APPLICATION_ID, recording_id=f"{RECORDING_ID}0")
        stream.save(str(layout), default_blueprint=blueprint(args.bounds))
        stream.disconnect()  # the file is complete only once its sink is closed
        shown = tmp / "shown.rrd"
        subprocess.run(["rerun", "rrd", "merge", str(layout), str(data), "-o", str(shown)],
                       check=True, capture_output=True)
        full = tmp / "full.png"
        subprocess.run(["rerun", "--headless", "--window-size", args.window_size,
                        "--screenshot-to", str(full), str(shown)], check=True, capture_output=True)
        image = Image.open(full)
        image.crop((0, 0, int(image.width * WORLD_SHARE) - 4, image.height)).save(args.out)
    print(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
