"""The 3D viewer: drawing frames with viser, the served app and its QA API (`mobileocc view`)."""
