"""Running a trained model: training checkpoints (:mod:`~pfnet.inference.checkpoint`), the
shipped model files (:mod:`~pfnet.inference.shipped`), the generator on PyTorch or ONNX
Runtime (:mod:`~pfnet.inference.runtimes`, :mod:`~pfnet.inference.devices`), the ONNX
export (:mod:`~pfnet.inference.onnx_export`, :mod:`~pfnet.inference.onnx_graph`),
predicting a data set's split (:mod:`~pfnet.inference.predict`,
:mod:`~pfnet.inference.benchmarks`) and completing your own clouds
(:mod:`~pfnet.inference.completion`)."""
