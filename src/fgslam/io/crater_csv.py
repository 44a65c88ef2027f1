"""Orbital crater catalogs as CSV (the crater kind's catalog layer): ``craters.csv`` in a
``fgslam sim`` directory, header ``x,y,size,score`` (world metres, size = rim diameter), the
format of the rock catalog and of ``fgslam catalog --landmark crater``; read with the rock
catalog's checks (:func:`fgslam.io.catalog_csv.read_catalog_csv`) into a
:class:`reloc.measurements.RockCatalog`-shaped catalog (``xy_m``, ``size_m``, ``score``)."""

from __future__ import annotations

from pathlib import Path

from fgslam.errors import InputFileError
from fgslam.io.catalog_csv import MIN_CATALOG_ROCKS, CatalogFile, read_catalog_csv
from reloc.measurements import RockCatalog


def read_crater_csv(path: str | Path) -> RockCatalog:
    """Read a crater catalog (see module doc); fewer than three craters is an error naming the file."""
    catalog = read_catalog_csv(path)
    if len(catalog) < MIN_CATALOG_ROCKS:
        raise InputFileError(f"{path}: the crater catalog holds {len(catalog)} craters; at least "
                             f"{MIN_CATALOG_ROCKS} are needed")
    return catalog


CRATER_CATALOG_FILE = CatalogFile("craters.csv", read_crater_csv)
