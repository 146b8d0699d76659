"""Strict JSON: non-finite numbers are written as null, so any JSON reader takes the file."""

import json
import math

import numpy as np
import pytest

from dipnet.core.strict_json import dumps, finite_or_none, write_json


def _refuse(word: str) -> None:
    raise ValueError(f"not strict JSON: {word}")


def test_a_metrics_dict_with_nan_and_inf_round_trips_as_strict_json(tmp_path):
    metrics = {"iou": 0.91, "hull_fill": math.nan, "height_trend_pivot_mm": np.float64("nan"),
               "limit": math.inf, "low": -math.inf, "n_dips": 40, "consistency": "consistent", "empty": False,
               "validation": {"totals_off": [28, 29], "spread": [1.0, math.nan]}, "pair": (math.inf, 2.0)}
    text = write_json(tmp_path / "metrics.json", metrics, indent=2).read_text()
    assert "NaN" not in text and "Infinity" not in text
    back = json.loads(text, parse_constant=_refuse)
    assert back == {"iou": 0.91, "hull_fill": None, "height_trend_pivot_mm": None, "limit": None, "low": None,
                    "n_dips": 40, "consistency": "consistent", "empty": False,
                    "validation": {"totals_off": [28, 29], "spread": [1.0, None]}, "pair": [None, 2.0]}


def test_the_value_itself_is_left_alone():
    values = {"a": [math.nan]}
    assert finite_or_none(values) == {"a": [None]} and math.isnan(values["a"][0])
    assert dumps(math.inf) == "null" and dumps({"b": 1.5}, sort_keys=True) == '{"b": 1.5}'


def test_other_non_json_values_still_fail():
    with pytest.raises(TypeError):
        dumps({"x": object()})
    assert dumps({"x": np.float32(1.0)}, default=str) == '{"x": "1.0"}'
