"""fednav-replay: publish a user's recorded logs over Zenoh as live sensors (see replay.__main__)."""
