"""The Dask settings ``afmdrift batch`` runs its own LocalCluster with, and
tells a cluster's owner to set (:data:`afmdrift.batch.DASK_SETTINGS`): each one
is a setting Dask has, its environment variable reads back as the same value,
the README lists the same variables, the command's scheduler and workers run
with them (also a worker the nanny restarts), and a setting the user
configured is kept."""

from __future__ import annotations

import copy
from pathlib import Path

import dask
import distributed  # also loads distributed's defaults into dask.config
import pytest

from afmdrift.batch import DASK_SETTINGS, dask_environ
from afmdrift.batch._run import _local_cluster, _unless_configured

README = Path(__file__).resolve().parents[2] / "README.md"


@pytest.fixture
def dask_defaults(monkeypatch: pytest.MonkeyPatch) -> None:
    """Dask's own defaults, whatever the developer's YAML files and ``DASK_...``
    variables say."""
    config: dict[str, object] = {}
    for d in dask.config.defaults:
        dask.config.update(config, copy.deepcopy(d))
    monkeypatch.setattr(dask.config, "config", config)
    monkeypatch.setattr(dask.config, "collect", lambda *args, **kwargs: {})


@pytest.mark.parametrize("key", sorted(DASK_SETTINGS))
def test_each_setting_is_one_dask_has(key: str) -> None:
    # a misspelt key would be accepted by dask.config.set and change nothing
    dask.config.get(key)  # raises KeyError for a setting Dask does not have


def test_the_environment_variables_read_back_as_the_settings() -> None:
    env = dask_environ()
    assert len(env) == len(DASK_SETTINGS)
    assert all(name.startswith("DASK_DISTRIBUTED__") for name in env)
    read = dask.config.collect_env(env)
    for key, value in DASK_SETTINGS.items():
        assert dask.config.get(key, config=read) == value


def test_the_readme_lists_the_same_variables() -> None:
    text = README.read_text(encoding="utf-8")
    for name, value in dask_environ().items():
        assert f"{name}={value}" in text


def worker_state(dask_worker: distributed.Worker) -> tuple[bool, float]:
    """Whether the worker profiles its tasks, and its tick interval (ms)."""
    tick = dask_worker.periodic_callbacks["tick"].callback_time
    return "profile" in dask_worker.periodic_callbacks, float(tick)


def scheduler_tick(dask_scheduler: distributed.Scheduler) -> float:
    return float(dask_scheduler.periodic_callbacks["tick"].callback_time)


def test_the_commands_local_cluster_runs_with_the_settings(dask_defaults: None) -> None:
    from distributed import Client

    with _local_cluster(1) as cluster, Client(cluster) as client:
        assert [tuple(v) for v in client.run(worker_state).values()] == [(False, 500)]
        assert client.run_on_scheduler(scheduler_tick) == 500
        client.restart()  # the nanny starts a new worker process
        assert [tuple(v) for v in client.run(worker_state).values()] == [(False, 500)]
    # the settings hold for the cluster only, not for the rest of the process
    assert dask.config.get("distributed.worker.profile.enabled") is True


def test_a_setting_the_user_changed_is_kept(dask_defaults: None) -> None:
    from distributed import Client

    with (
        dask.config.set({"distributed.admin.tick.interval": "50ms"}),
        _local_cluster(1) as cluster,
        Client(cluster) as client,
    ):
        assert client.run_on_scheduler(scheduler_tick) == 50  # the user's
        assert [tuple(v) for v in client.run(worker_state).values()] == [(False, 50)]


def test_a_setting_the_users_configuration_names_is_kept_even_at_dasks_default(
    dask_defaults: None, monkeypatch: pytest.MonkeyPatch
) -> None:
    key = "distributed.worker.profile.enabled"
    assert key in _unless_configured(DASK_SETTINGS)  # nothing configured
    # the profiler asked for explicitly, by the value Dask has anyway
    named = dask.config.collect_env({"DASK_DISTRIBUTED__WORKER__PROFILE__ENABLED": "True"})
    monkeypatch.setattr(dask.config, "collect", lambda *args, **kwargs: named)
    assert key not in _unless_configured(DASK_SETTINGS)
    assert "distributed.admin.tick.interval" in _unless_configured(DASK_SETTINGS)
