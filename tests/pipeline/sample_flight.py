"""Texts of a small hand-written flight folder, and the simulated test flight's settings."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from seqat.simulate import StripSimConfig

FLIGHT_YAML = """\
crs: EPSG:32652
camera:
  model: PINHOLE
  width_px: 640
  height_px: 480
  fx_px: 1000.0
  fy_px: 1000.0
  cx_px: 319.5
  cy_px: 239.5
nav:
  file: nav.csv
  frame: projected
  sigma_position_m: 0.3
  sigma_attitude_deg: [0.1, 0.1, 0.2]
sigma_image_px: 1.5
observations: observations.csv
"""

NAV_CSV = """\
image,time_s,x_m,y_m,z_m,omega_deg,phi_deg,kappa_deg
img_1,0.0,500000.0,4090000.0,300.0,0.5,-0.25,90.0
img_2,0.5,500005.0,4090000.1,300.2,0.4,-0.2,90.1
img_3,1.0,500010.0,4090000.2,300.1,0.3,-0.1,89.9
img_4,1.5,500015.0,4090000.3,300.0,0.2,0.0,90.0
"""

OBSERVATIONS_CSV = """\
image,point,x_px,y_px
img_1,p1,100.0,200.0
img_1,p2,300.5,250.25
img_2,p1,80.0,201.0
img_2,p2,280.5,251.0
img_2,p3,500.0,100.0
img_4,p3,450.0,101.0
img_4,p4,10.0,11.0
"""

#: Files of the hand-written flight, by name.
FLIGHT_FILES = {"flight.yaml": FLIGHT_YAML, "nav.csv": NAV_CSV,
                "observations.csv": OBSERVATIONS_CSV}

#: A small simulated strip: fast, but long enough for the sequential stage to run.
SMALL_SIM = StripSimConfig(n_images=24, n_points=40)
#: Seed of the simulated test flight.
SIM_SEED = 7
#: CRS of the simulated test flight.
SIM_CRS = "EPSG:32652"

#: ``make_flight(**files) -> flight folder`` (fixture in conftest.py).
FlightMaker = Callable[..., Path]
