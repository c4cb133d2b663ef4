"""One grammar for option values (neural_estimator.core.options), the same in every place that parses text."""

from __future__ import annotations

import pytest

from neural_estimator.core.options import OptionError, parse_bool, parse_value


@pytest.mark.parametrize(
    "text, value",
    [
        ("true", True),
        ("Yes", True),
        ("ON", True),
        ("1", True),
        ("false", False),
        ("no", False),
        ("off", False),
        ("0", False),
    ],
)
def test_booleans(text, value):
    assert parse_bool(text) is value and parse_value(text, False, "flag") is value


@pytest.mark.parametrize(
    "value, like, expect",
    [
        ("3", 1, 3),
        ("3.0", 1, 3),
        ("1e3", 1, 1000),
        (7, 1, 7),
        ("0.5", 1.0, 0.5),
        ("inf", 1.0, float("inf")),
        (2, 1.0, 2.0),
        ("abc", "", "abc"),
        ("[1, 2.5]", (0.0, 0.0), (1.0, 2.5)),
        ("1,2.5", (0.0, 0.0), (1.0, 2.5)),
        ([[1, 0], [0, 1]], ((0.0, 0.0), (0.0, 0.0)), ((1.0, 0.0), (0.0, 1.0))),
        ("a,b", ("",), ("a", "b")),
        ("", ("",), ()),
    ],
)
def test_typed_by_the_default(value, like, expect):
    assert parse_value(value, like, "x") == expect


@pytest.mark.parametrize(
    "value, like, message",
    [
        ("maybe", False, "x must be true or false"),
        ("2.5", 1, "x must be an integer"),
        (True, 1, "x must be an integer"),
        ("abc", 1.0, "x must be a number"),
        ("[1, 2, 3]", (0.0, 0.0), "x must have the shape"),
        ("none", 1.0, "x must be a number"),
    ],
)
def test_errors_name_the_option(value, like, message):
    with pytest.raises(OptionError, match=message) as err:
        parse_value(value, like, "x")
    assert "\n" not in str(err.value)


def test_none_where_the_field_may_be_none():
    assert parse_value("none", 1.0, "init_std", optional=True) is None
    assert parse_value("NULL", 1.0, "init_std", optional=True) is None
    assert parse_value("2", 1.0, "init_std", optional=True) == 2.0


def test_every_parser_of_the_package_speaks_the_same_grammar():
    """'yes' is a bool for a scenario constant, a filter option, a neural option and a node parameter."""
    from neural_estimator.methods.registry import EstimatorError, make_estimator
    from neural_estimator.filters.base import build_hyperparams
    from neural_estimator.filters.ekf import EKFHyperParams
    from neural_estimator.filters.pf import ParticleFilter
    from neural_estimator.scenarios import ScenarioError, make_scenario

    assert build_hyperparams(EKFHyperParams, "ekf", None, {"joseph_form": "no"}).joseph_form is False
    s = make_scenario("lorenz96")
    assert ParticleFilter(s, init_std="none", n_particles="16").hp.init_std is None  # the PF's prior draw
    assert make_estimator("filterformer", s, covariance="off").has_covariance is False
    assert make_estimator("filterformer", s, covariance="on").has_covariance is True
    with pytest.raises(EstimatorError, match="compile_step must be true or false"):
        make_estimator("gru", s, compile_step="sometimes")
    with pytest.raises(ScenarioError, match="n_vars must be an integer"):
        make_scenario("lorenz96", n_vars="ten")
    assert make_scenario("nlink", prior_angle_std="0.2").config.prior_angle_std == 0.2

    pytest.importorskip("rclpy")
    from neural_estimator.nodes.common import StartupError, _coerce

    assert _coerce("flag", "yes", bool, False) is True and _coerce("flag", "off", bool, True) is False
    assert _coerce("topics", "a, b", tuple[str, ...], ()) == ("a", "b")
    with pytest.raises(StartupError, match="parameter depth must be an integer"):
        _coerce("depth", "deep", int, 1)
