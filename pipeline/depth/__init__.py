"""Stage ``depth``: sparse depth from the SfM tracks."""
