"""Operating the running daemon across its rooms: the status it reports and the reload that
applies a judged config."""
