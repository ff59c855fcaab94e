"""The names of the synthetic catalogs (``data.source.catalog``), in a module that imports nothing.

:mod:`matl.data.catalog` builds them and config validation (:mod:`matl.utils.config`) checks a
name against them; importing the catalog package itself takes seconds (matplotlib, trimesh), so
both read the names from here.
"""

from __future__ import annotations

# apc, arc and ycb are compositions of the paper's datasets (matl.data.catalog.products.CATALOG_COMPOSITIONS);
# ycb_table2 is ycb split for Table 2 (11 simple and 23 non-planar objects).
SYNTHETIC_CATALOGS = ("apc", "arc", "ycb", "ycb_table2")
