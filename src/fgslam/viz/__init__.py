"""Visualisation: matplotlib PNGs (:mod:`fgslam.viz.plots`) and the rerun recording (:mod:`fgslam.viz.rerun_log`)."""
