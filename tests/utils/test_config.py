"""Config validation: the synthetic catalogs' names are defined once, here, and reading them loads no data code."""

from __future__ import annotations

import subprocess
import sys

from matl.data.catalog import CATALOG_COMPOSITIONS, CATALOGS
from matl.utils.config import SYNTHETIC_CATALOGS


def test_one_definition_of_the_names() -> None:
    assert CATALOGS is SYNTHETIC_CATALOGS  # matl.data.catalog builds the catalogs validation accepts
    assert set(SYNTHETIC_CATALOGS) == {*CATALOG_COMPOSITIONS, "ycb_table2"}  # every composition has its name


def test_validation_does_not_import_the_catalog() -> None:
    code = "import sys, matl.utils.config; print(sorted(m for m in sys.modules if m.startswith('matl.data')))"
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert loaded.strip() == "[]"
