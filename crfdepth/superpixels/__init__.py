"""SLIC superpixels, their label maps and the region graph the CRF runs on (docs/design.md section 2)."""
