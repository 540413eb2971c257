"""Stages from photos to a textured mesh; each calls ``dvr/`` (never the reverse)."""
