"""The scene-independent machinery: compiled block helpers (`blocks`) and the one launch (`launch`)."""
