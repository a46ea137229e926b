"""Training and evaluation of VGQ-CNN, Fast-VGQ-CNN and the GQ-CNN baseline (torch).

Modules: ``config`` (TrainConfig), ``data`` (crop datasets), ``train``, ``evaluate``,
``metrics``, ``plots``, ``baseline`` (pose-only), ``ablation`` (kappa), ``checkpoint``
(run folders, ``load_trained``), ``synthetic`` (writing crop datasets), ``bench``.
CLI: ``python -m training --help``.
"""


def __getattr__(name):  # lazy: ``from training import load_trained`` without importing torch early
    if name == "load_trained":
        from .checkpoint import load_trained

        return load_trained
    raise AttributeError(f"module 'training' has no attribute {name!r}")
