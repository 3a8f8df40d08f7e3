"""Who may pick the model: open on a local-only server, locked behind a share link or LAN address."""

from pathlib import Path

import pytest

from relight_core.errors import InputError
from ui.server import ServerOptions
from ui.studio import Studio, StudioConfig

ROOT = Path(__file__).resolve().parent.parent


def test_model_choice_is_open_only_on_a_local_server():
    assert ServerOptions().visitors_choose_model
    assert not ServerOptions(share=True).visitors_choose_model
    assert not ServerOptions(host="0.0.0.0").visitors_choose_model
    assert ServerOptions(share=True, model_choice=True).visitors_choose_model
    assert not ServerOptions(model_choice=False).visitors_choose_model


def test_a_fixed_model_refuses_other_folders(tmp_path):
    studio = Studio(StudioConfig(model="tiny", envmaps_dir=ROOT / "envmaps", work_dir=tmp_path / "work",
                                 model_choice=False))
    with pytest.raises(InputError, match="fixed model"):
        studio.relighter(str(tmp_path))
    assert studio.relighter("") is studio.relighter("tiny")
