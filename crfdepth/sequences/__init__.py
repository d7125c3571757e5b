"""Learning from recordings: poses, camera-view targets, free space and the photometric loss
(docs/design.md sections 12-15)."""
