"""Column schemas and file names of the pipeline's CSV files and folders (docs/formats.md)."""

#: Columns of the output ``eop.csv``.
EOP_COLUMNS = ("image", "x_m", "y_m", "z_m", "omega_deg", "phi_deg", "kappa_deg",
               "sx_m", "sy_m", "sz_m", "somega_deg", "sphi_deg", "skappa_deg")
#: Columns of the output ``points.csv``.
POINT_COLUMNS = ("point", "x_m", "y_m", "z_m", "sx_m", "sy_m", "sz_m", "n_obs")
#: File names inside a run's output folder.
EOP_FILE = "eop.csv"
POINTS_FILE = "points.csv"
RUN_FILE = "run.json"
NAV_FILE = "nav.csv"
OBSERVATIONS_FILE = "observations.csv"
#: Columns of a projected ``nav.csv`` (flight input and run output).
NAV_COLUMNS = ("image", "time_s", "x_m", "y_m", "z_m", "omega_deg", "phi_deg", "kappa_deg")
#: Columns of ``observations.csv`` (flight input and run output).
OBS_COLUMNS = ("image", "point", "x_px", "y_px")
#: Optional column of ``observations.csv``: the frame (image update) a row arrived with; a
#: row of an earlier image than its frame is a late observation (docs/formats.md). Without
#: it every row arrived with its own image.
OBS_FRAME_COLUMN = "frame"
#: Columns of a run's ``observations.csv`` (always with the frame).
RUN_OBS_COLUMNS = (*OBS_COLUMNS, OBS_FRAME_COLUMN)
#: Name of the flight description inside a flight folder.
FLIGHT_YAML = "flight.yaml"
#: Folder of the exact truth of simulated flights.
TRUTH_DIR = "truth"
#: Default image sub-folder of a bare flight folder.
IMAGES_DIR = "images"
#: Columns of a geodetic ``nav.csv``.
NAV_GEODETIC_COLUMNS = ("image", "time_s", "lat_deg", "lon_deg", "h_m", "roll_deg",
                        "pitch_deg", "yaw_deg")
#: Columns of ``truth/points.csv`` and ``checkpoints.csv``.
GROUND_POINT_COLUMNS = ("point", "x_m", "y_m", "z_m")
#: Check points of a flight folder (known ground coordinates) and their image observations.
CHECKPOINTS_FILE = "checkpoints.csv"
CHECKPOINT_OBS_FILE = "checkpoint_obs.csv"
#: The COLMAP reference of a run, inside its run folder (``seqat reference``).
REFERENCE_DIR = "reference"
#: ``OUT/live/``: what a live run publishes for ``seqat serve`` while it goes on
#: (docs/formats.md, *Live run files*): the current estimates, the live mosaic's index and
#: its tiles.
LIVE_DIR = "live"
LIVE_ESTIMATES_FILE = "estimates.json"
LIVE_MOSAIC_INDEX = "mosaic.json"
LIVE_TILES_DIR = "tiles"
LIVE_QUICKLOOK_DIR = "quicklook"
#: The independent SfM check inside it (``seqat reference OUT --sfm``).
SFM_DIR = "sfm"
