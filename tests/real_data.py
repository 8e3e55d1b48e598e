"""Paths of the real GNSS data shared beside the project (``../shared/data/real``)."""

from pathlib import Path

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"
SP3_FILE = DATA / "orbits_2021_118" / "COD0MGXFIN_20211180000_01D_05M_ORB.SP3"
BRDC_2021 = DATA / "orbits_2021_118" / "brdc1180.21n"
WUHAN = DATA / "psins_wuhan_2015"
BRDC_2015 = WUHAN / "01.15n"
