"""Adapters for real perception networks: pre-processing, decoding, and a composite per setup.

An adapter never opens a file. It takes a *runner*: an object with ``source`` (a name for error
messages, e.g. the model file), ``input_shapes`` and ``output_shapes`` (name -> shape, ``None``
for a dynamic axis) and ``__call__(feeds: dict[str, ndarray]) -> dict[str, ndarray]``
(:class:`tasks.perception.models.runner.ModelRunner`). ``storage.network_files`` opens ONNX files
(onnxruntime) and TFLite files (ai-edge-litert) into runners; tests build tiny ONNX models or
plain Python fakes.

Pixels: images are (H, W, 3) uint8 RGB; image coordinates follow OpenCV (pixel (c, r) has its
centre at (u, v) = (c, r)), as the synthetic camera renders (tasks.sim.sensors.camera_rays) and
as the model families' own code (YOLOX, mmpose, CLIFF) measures. Crops are 2 x 3 affine maps from
image to model-input pixels in that same convention.

Modules: :mod:`.image` (letterbox, affine crops, paste-back, NMS), :mod:`.detector` (YOLOX and
decoded boxes), :mod:`.keypoints` (ViTPose heatmaps, RTMPose SimCC), :mod:`.segmentation`
(Cityscapes semantics, Mask2Former masks, the semantic-person fallback), :mod:`.cliff` (initial
bodies), :mod:`.blazepose` (the bundled MediaPipe models), :mod:`.composite` (one image ->
:class:`tasks.perception.types.ImagePerception`).
"""
