"""Facts about the capture that several stages read: the support plane and the photos' exposure."""
