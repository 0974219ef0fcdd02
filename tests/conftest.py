"""Shared pytest setup: tests marked ``cuda`` skip cleanly on machines without a CUDA GPU.

On a GPU machine, ``python -m pytest -m cuda`` runs exactly the GPU checks.
"""

import pytest
import torch


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if torch.cuda.is_available():
        return
    skip = pytest.mark.skip(reason="needs a CUDA GPU (on one, `python -m pytest -m cuda` runs these)")
    for item in items:
        if item.get_closest_marker("cuda") is not None:
            item.add_marker(skip)
