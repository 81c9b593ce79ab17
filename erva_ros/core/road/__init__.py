"""Roads: profiles (paper, ISO 8608, recorded), a car's two tracks, preview error."""
