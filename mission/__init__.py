"""The composition root: the ``magic`` command, configuration loading, launching, evaluation."""
