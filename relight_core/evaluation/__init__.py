"""Evaluation: the paper's metrics and a harness that measures any model on a rendered dataset.

`python -m relight_core evaluate --data DIR --split test --model M` (cli.py) writes metrics.json,
metrics.md and image grids; `metrics` holds the PSNR/SSIM protocol, `harness` the measurements,
`runner` one whole run, `report` what people read.
"""

from relight_core.evaluation.metrics import protocol_metrics, psnr, scale_fit, ssim

__all__ = ["protocol_metrics", "psnr", "scale_fit", "ssim"]
