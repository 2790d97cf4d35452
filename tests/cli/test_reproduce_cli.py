"""``gravcal reproduce``: the defaults --help states are the ones the code runs with, and bad options
give one line naming the problem."""
from __future__ import annotations

import argparse
import re

import numpy as np
import pytest

from gravcal.core.reproduce_config import ReproduceConfig, theta_grid
from gravcal.cli.main import build_parser, main
from gravcal.cli.cmd_reproduce import OPTION_FIELDS


def reproduce_parser() -> argparse.ArgumentParser:
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices["reproduce"]


def test_every_option_defaults_to_the_config_and_help_says_so():
    parser = reproduce_parser()
    args = parser.parse_args(["loetters"])
    config = ReproduceConfig()
    helps = {a.dest: a.help % {"default": a.default} for a in parser._actions if a.help and a.dest in OPTION_FIELDS}
    assert set(helps) == set(OPTION_FIELDS)  # every option mapped to the config has a help line
    for dest, field in OPTION_FIELDS.items():
        value = getattr(args, dest)
        if field is None:  # the grid step: the grid it builds is the config's grid
            assert np.array_equal(theta_grid(value), config.theta_deg), dest
        else:
            assert value == getattr(config, field), (dest, value, getattr(config, field))
        assert re.search(rf"\(default {re.escape(str(value))}\)", helps[dest]), (dest, helps[dest])
    rendered = re.sub(r"\s+", " ", parser.format_help())
    assert f"(default {config.seeds})" in rendered and f"(default {config.c_mu_reading})" in rendered


@pytest.mark.parametrize("argv, fragment", [
    (["--seeds", "0"], "--seeds"),
    (["--points", "3"], "--points"),
    (["--theta-step", "0"], "--theta-step"),
    (["--held-sensitivity-error", "1.5"], "--held-sensitivity-error"),
])
def test_bad_options_name_the_problem(capsys, argv, fragment):
    code = main(["reproduce", "loetters", *argv])
    err = capsys.readouterr().err
    errors = [ln for ln in err.splitlines() if ln.startswith("gravcal: error: ")]
    assert code == 2 and len(errors) == 1 and fragment in errors[0] and "Traceback" not in err, err
