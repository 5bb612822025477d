"""The scene teachers as torch modules, run at inference by the ``scene`` depth source.

Each teacher is a small pretrained network, written here as a torch module, with weights
converted once from its original file (``d2f-train port-teachers``, training-time extras only)
and shipped in ``assets/weights/`` beside a notice naming each one's origin and licence
(``assets/weights/TEACHERS.md``). At inference only torch is needed.

- :mod:`.deeplab`: DeepLabV3 with a MobileNetV2 backbone (ADE20K scene parsing, 151 classes;
  PASCAL VOC objects, 21 classes);
- :mod:`.u2net`: U^2-Net-p salient-object silhouettes;
- :mod:`.fastdepth`: FastDepth indoor depth.
"""
