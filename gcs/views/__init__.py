"""Operator views (paper 6): the picture of the GCS state and the one rerun adapter.

:mod:`gcs.views.operator_picture` (rerun-free snapshot and publishing schedule),
:mod:`gcs.views.alerts` (dashboard alert rules), :mod:`gcs.views.narration` (SAGE events),
:mod:`gcs.views.render` (offscreen cv2 drawings: SAGE zooms, SOC thumbnails, debug PNG),
:mod:`gcs.views.rerun_views` (the only module of the project that imports rerun) and
:mod:`gcs.views.trial` (feed a replay through the views, write a recording, measure the cost).
"""
