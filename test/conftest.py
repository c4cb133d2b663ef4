"""Shared fixtures: the example user scenario (a linear-Gaussian oscillator) is registered here."""

import ast
import importlib.util
import os
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _load_example():
    spec = importlib.util.spec_from_file_location("custom_scenario_example", ROOT / "examples" / "custom_scenario.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # so the class's source file is known (plugins loaded twice are the same)
    spec.loader.exec_module(module)
    return module


EXAMPLE = _load_example()


def pytest_configure(config):
    # The fast suite, for a contributor's inner loop (docs/architecture.md, "Checks"):
    #   pytest -m "not ros and not slow and not colcon"
    # scripts/run_tests.sh runs everything.
    config.addinivalue_line("markers", "ros: starts ROS 2 nodes or a ROS graph (rclpy processes, DDS discovery)")
    config.addinivalue_line(
        "markers", "slow: a second or more on its own (live runs, training, statistical references, subprocesses)"
    )
    config.addinivalue_line("markers", "colcon: builds the package as a ROS 2 workspace with colcon")
    _confine_worker_domains()


def _confine_worker_domains() -> None:
    """Under pytest-xdist (scripts/run_tests.sh runs the suite on two workers), each worker takes its own
    share of ``NEURAL_ESTIMATOR_DOMAINS`` (default 200..232), so that two workers' ROS tests never meet
    on one domain: every ROS test and tool picks its domain from that variable."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")
    if not worker.startswith("gw"):
        return
    from ros_tester import TEST_DOMAINS

    from neural_estimator.nodes.launch import DOMAINS_VARIABLE, domain_range

    count, index = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")), int(worker[2:])
    lo, hi = domain_range(TEST_DOMAINS)
    share = (hi - lo + 1) // count
    if share < 1:
        raise pytest.UsageError(f"{DOMAINS_VARIABLE}={lo}-{hi}: fewer ROS domains than the {count} test workers")
    os.environ[DOMAINS_VARIABLE] = f"{lo + index * share}-{lo + (index + 1) * share - 1}"


def load_script(relative: str):
    """A repository script (``scripts/...``, ``benchmarks/...``, ``experiments/...``) loaded afresh as a module, so its
    functions and ``main`` are tested in-process (each call gives a new module: monkeypatching one
    test's copy leaves the others alone)."""
    path = ROOT / relative
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def top_level_imports(path: Path) -> set[str]:
    """The top-level modules a Python file imports (absolute imports only)."""
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(a.name.split(".")[0] for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
    return names


@pytest.fixture
def oscillator():
    """The documented custom scenario (docs/scenarios.md): linear-Gaussian, so the Kalman filter is exact."""
    return EXAMPLE.Oscillator()


@pytest.fixture
def spinner():
    """A small controlled system with an angular state (training_cases.Spinner: the neural-estimator,
    checkpoint, training and zoo tests)."""
    from training_cases import Spinner

    return Spinner()


@pytest.fixture(scope="module")
def one_torch_thread():
    """Small models on a shared 2-core machine: one intra-op thread avoids spin-wait contention
    (a test module opts in with ``pytestmark = pytest.mark.usefixtures("one_torch_thread")``)."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


# ---- the live node tests (test/test_nodes_*.py; node_cases.py) ------------------------------------------
@pytest.fixture(scope="module")
def plugin(tmp_path_factory) -> str:
    """The node tests' scenario (node_cases.PLUGIN, a cart pushed by a force) as a plugin file."""
    from node_cases import PLUGIN

    path = tmp_path_factory.mktemp("plugin") / "nodecart.py"
    path.write_text(PLUGIN)
    return str(path)


@pytest.fixture(scope="module")
def cart(plugin):
    import importlib.util

    spec = importlib.util.spec_from_file_location("nodecart_plugin", plugin)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.NodeCart()


@pytest.fixture
def domain() -> int:
    """A ROS domain of its own for each test (ros_tester.fresh_domain: NEURAL_ESTIMATOR_DOMAINS or 200..232)."""
    from ros_tester import fresh_domain

    return fresh_domain()


@pytest.fixture
def nodes(domain, tmp_path):
    """The node processes of one test (node_cases.Nodes), stopped at its end."""
    from node_cases import Nodes

    n = Nodes(domain, tmp_path)
    yield n
    n.stop_all()
