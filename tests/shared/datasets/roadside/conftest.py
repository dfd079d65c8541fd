from __future__ import annotations

import pytest

from shared.datasets.roadside.model import RoadsideDataset
from shared.datasets.roadside.openlabel import read_openlabel
from shared.paths import REPO_ROOT

REAL = REPO_ROOT / "tests" / "fixtures" / "real"
TUMTRAF = REAL / "tumtraf_a9"
ROPE3D = REAL / "rope3d"


@pytest.fixture(scope="session")
def tumtraf() -> RoadsideDataset:
    return read_openlabel(TUMTRAF)
