"""File formats of fgslam: rock catalogs (CSV), trajectories (TUM) and ROS 2 bags.

The bag reader (and rosbags behind it) is imported on first use, so that importing
``fgslam.io`` for a catalog or a trajectory stays cheap.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from fgslam.io.catalog_csv import read_catalog_csv, write_catalog_csv
from fgslam.io.tum import read_tum, write_tum

if TYPE_CHECKING:
    from fgslam.io.bag_decode import BagReaderConfig
    from fgslam.io.bag_reader import BagReport, BagStream, TopicReport, read_bag
    from reloc.bag_spec import TopicNames

_LAZY = {
    "read_bag": "fgslam.io.bag_reader",
    "BagStream": "fgslam.io.bag_reader",
    "BagReport": "fgslam.io.bag_reader",
    "TopicReport": "fgslam.io.bag_reader",
    "BagReaderConfig": "fgslam.io.bag_decode",
    "TopicNames": "reloc.bag_spec",
}

__all__ = [
    "BagReaderConfig",
    "BagReport",
    "BagStream",
    "TopicNames",
    "TopicReport",
    "read_bag",
    "read_catalog_csv",
    "read_tum",
    "write_catalog_csv",
    "write_tum",
]


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'fgslam.io' has no attribute {name!r}")
