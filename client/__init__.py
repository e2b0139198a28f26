"""Player, viewer and the `posecast` command line."""
