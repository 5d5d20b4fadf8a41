"""What the 3D viewer shows, as plain arrays: the scene of a frame (:mod:`tasks.view.scene`) and
the manual detection QA (:mod:`tasks.view.qa`). No viewer library, file or clock here: the viewer
(flows/viewer/) reads through storage/ and draws these."""
