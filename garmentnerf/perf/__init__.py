"""Speed/accuracy settings of rendering (presets) and their measurement."""
