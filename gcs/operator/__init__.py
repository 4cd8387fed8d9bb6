"""The operator side of the GCS (paper 6.2): the command language (:mod:`.grammar`), the
command handler (:mod:`.handler`: a command in, effects on the station and tasks out) and the
service the GCS node runs (:mod:`.service`: authenticated commands over zenoh, status for
consoles, interaction and autonomy-mode metrics, the rerun views)."""
