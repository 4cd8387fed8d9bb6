"""Real laser logs for the GCS: CARMEN log reader, relations error metric (issue 7 item 7)."""
