"""simgen: procedural urban scenes rendered into a nuScenes-format dataset."""
