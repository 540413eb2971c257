"""Stage ``masks``: object masks, automatic or the user's."""
