"""keypoints stage: per-view multi-person 2D keypoints through ONNX models.

- ``registry``: model descriptions (``keypoints/models/*.toml``, plus user ``*.toml`` in a model folder),
  model folders (``--model-dir`` / ``ROOMCAP_MODELS`` / ``$ROOMCAP_SHARED/models`` / the cache
  ``~/.cache/roomcap/models``), sha256 checks and ``fetch`` (OpenMMLab SDK zips unpacked);
- ``runtime``: onnxruntime sessions (provider choice, threads, dynamic batch made once at load, warm-up);
- ``decoders``: YOLOX grid + NMS, mmdeploy dets, BlazePose, MoveNet, RTMPose SimCC, RTMO, OpenPose PAF;
- ``pipeline``: ``KeypointPipeline`` top-down (detector -> crops -> pose, with an upright refine pass) and
  bottom-up (maps kept for the tracker); output in full-image pixels, ``body19`` (the canonical skeleton
  every 3D stage reads);
- ``video``: ``run_session`` / ``run_videos``: threaded decoding, batched across cameras, resumable chunks;
- ``cli``: the ``keypoints`` console script (``list``, ``fetch``, ``run``).
"""
