"""Stage ``texture``: the clean mesh UV-textured from the photos."""
