"""Network training (torch, the ``train`` extra), moved out of ``edge_agent``: the detector, the
keypoint network and the segmentation network the edge agent runs.

- ``data``: training data: labelled renders from a view source the top floor provides, turned
  into the networks' inputs with the deployed pre-processing;
- ``nets``: the networks in plain torch (no torchvision), sized for an edge board;
- ``train``: train, validate and export them (ONNX file, model card);
- ``targets``: what the networks are trained towards (heat maps, SimCC targets, losses, weights);
- ``onnx_init``: start a training run from an exported ONNX model.

Imports the ground floor of the project (``protocol`` and ``core``) and ``edge_agent`` (its
crops, model cards and metrics); never the simulation (``lab.training_views`` provides it).
"""
