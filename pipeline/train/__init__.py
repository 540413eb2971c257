"""Stage ``train``: the DVR fields trained (the method itself lives in ``dvr/``)."""
