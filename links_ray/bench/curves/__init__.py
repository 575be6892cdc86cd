"""The curve sets the synthesis benchmark measures with: letters of two fonts, gaits, cams,
random smooth and self-crossing curves, curves real mechanisms trace, and GCP-HOLO's published
test curves (`gcp_holo_curves.json`)."""
