"""The `monoloc` command: the composition root that ties server, sim and client CLIs."""
