"""A candidate model folder: the shipped model with refiners swapped in, their weights rounded to bf16 as they ship.
    PYTHONPATH=. python runs/refiner-copies/candidate.py OUT [--relit RELIT.safetensors] [--albedo ALBEDO.safetensors]
Strengths are reset to 1 (as trained) for each refiner swapped in; calibrate them afterwards.
"""
import argparse
import json
import shutil
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file

parser = argparse.ArgumentParser()
parser.add_argument("out", type=Path)
parser.add_argument("--relit", type=Path)
parser.add_argument("--albedo", type=Path)
args = parser.parse_args()
shutil.rmtree(args.out, ignore_errors=True)
shutil.copytree("models/default", args.out)
config = json.loads((args.out / "config.json").read_text())
for source, slot, file in ((args.relit, "relit_refiner", "relit_refiner.safetensors"),
                           (args.albedo, "refiner", "refiner.safetensors")):
    if source is None:
        continue
    save_file({k: v.to(torch.bfloat16).contiguous() for k, v in load_file(source).items()}, args.out / file)
    config[slot].pop("strength", None)
    print(f"{slot}: {source}")
(args.out / "config.json").write_text(json.dumps(config, indent=2))
