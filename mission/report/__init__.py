"""The mission report (issue 14 item 3; paper section 7): :class:`MissionRecorder` records a
run into its run directory; :func:`~mission.report.report_builder.build_report` scores it
against the truth and writes ``report.json``, ``report.md`` and ``plots/*.png``
(``magic report RUN_DIR``)."""
