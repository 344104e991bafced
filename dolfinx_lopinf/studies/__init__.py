"""Study tools: what the demos and experiments share (not the library's numerical layers)."""
