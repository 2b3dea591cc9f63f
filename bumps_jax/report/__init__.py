"""Reports of a finished run: tables, figures, README blocks, publishing."""
