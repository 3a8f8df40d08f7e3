"""Evaluation: the paper's metrics and a harness that measures any model on a rendered dataset.

`python -m relight_core evaluate --data DIR --split test --model M` (cli.py) writes metrics.json,
metrics.md and image grids; `metrics` holds the PSNR/SSIM protocol, `harness` the measurements,
`runner` one whole run, `report` what people read.
"""

__all__ = ["protocol_metrics", "psnr", "scale_fit", "ssim"]


def __getattr__(name: str):
    """The metrics on first use, so that building the CLI's parser does not import torch."""
    if name in __all__:
        from relight_core.evaluation import metrics

        return getattr(metrics, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
