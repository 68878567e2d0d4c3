"""Messages that named the wrong thing: a data key naming a folder ("names a missing
file"), a config saved with a byte order mark ("not valid TOML (line 1, column 1)")."""

from __future__ import annotations

import pytest

from ecmgen.config import load_config
from ecmgen.errors import InputError

CONFIG = '[cell]\ncapacity_ah = 2.9\n[data]\npulses = "pulses.csv"\nocv = "pulses"\n'


def test_a_data_key_naming_a_folder_says_folder(tmp_path):
    (tmp_path / "pulses.csv").mkdir()
    cfg = tmp_path / "c.toml"
    cfg.write_text(CONFIG)
    with pytest.raises(InputError, match=r"data\.pulses names a folder, not a file"):
        load_config(cfg)


def test_a_config_with_a_byte_order_mark_is_read(tmp_path):
    (tmp_path / "pulses.csv").write_text("time_s,current_a,voltage_v\n0,0,3.7\n")
    cfg = tmp_path / "c.toml"
    cfg.write_bytes(b"\xef\xbb\xbf" + CONFIG.encode())
    assert load_config(cfg).capacity_ah == 2.9
