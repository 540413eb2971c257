"""Stage ``report``: report.html from everything in the workspace."""
