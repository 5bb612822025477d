"""Training, apart from inference: the EBB! pairs (:mod:`.data`), the losses (:mod:`.losses`),
generated scenes (:mod:`.synth`), the two-stage training of D2F (:mod:`.two_stage`,
``d2f-train``), and stage 0, the depth network trained on labelled photos.

Nothing on the inference path (pipeline, rendering, networks, io, depth) imports this package.
"""
