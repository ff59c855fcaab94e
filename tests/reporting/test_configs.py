"""Reading saved configs: dataset names, and fingerprints that group a configuration's seeds."""

from __future__ import annotations

from omegaconf import OmegaConf

from matl.reporting.configs import config_container, dataset_name, fingerprint, select, short


def test_configs_that_resolve_alike_group_together() -> None:
    def run(t_max: object, seed: int) -> str:
        trainer = {"max_epochs": 8, "default_root_dir": "${hydra:runtime.output_dir}"}  # unresolvable here
        cfg = OmegaConf.create({"seed": seed, "trainer": trainer, "data": {"seed": "${seed}"},
                                "model": {"scheduler": {"T_max": t_max}}})
        return fingerprint(config_container(cfg))

    assert run(8, 0) == run("${trainer.max_epochs}", 1) == run("${trainer.max_epochs}", 2)  # seeds of one setting
    assert run(4, 0) != run(8, 0)


def test_dataset_names() -> None:
    def data(source: dict, queries: str | None = None):
        return OmegaConf.create({"source": source, "queries": queries})

    synthetic = "matl.data.catalog.SyntheticCatalog"
    assert dataset_name(data({"_target_": synthetic, "catalog": "arc"})) == "synthetic_arc"
    assert dataset_name(data({"_target_": synthetic, "catalog": "ycb", "subset": "planar"})) == "synthetic_ycb"
    assert dataset_name(data({"_target_": synthetic, "catalog": "ycb", "subset": "all"})) == "synthetic_ycb/all"
    assert dataset_name(data({"_target_": synthetic, "catalog": "ycb_table2"})) == "synthetic_ycb_table2/all"
    assert dataset_name(data({"_target_": synthetic, "catalog": "apc"}, "rendered")) == "synthetic_apc+rendered"
    assert dataset_name(data({"_target_": "matl.data.meshes.YCBSource", "subset": "planar"})) == "ycb/planar"
    assert dataset_name(data({"_target_": "matl.data.meshes.YCBSource"}), choice="my_ycb") == "my_ycb"


def test_select_and_short_tolerate_what_only_resolves_inside_a_run() -> None:
    cfg = OmegaConf.create({"paths": {"out": "${hydra:runtime.output_dir}"}, "model": {"_target_": "matl.models.X"}})
    assert select(cfg, "paths.out", "?") == "?" and select(cfg, "missing.key") is None and select(None, "a", 1) == 1
    assert short(select(cfg, "model._target_")) == "X" and short("other.Y") == "other.Y" and short(None) is None
