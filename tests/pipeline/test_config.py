"""The typed configuration: defaults, YAML and CLI overrides, errors that name the key."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from pipeline import config as config_module
from pipeline.config import ConfigError, PipelineConfig, load_config

REPO = Path(__file__).resolve().parents[2]


def test_committed_defaults_file_matches_the_code_defaults() -> None:
    committed = yaml.safe_load((REPO / "configs" / "pipeline.yaml").read_text())
    assert committed == PipelineConfig().model_dump(mode="json")


def test_yaml_files_apply_in_order_and_dotted_overrides_win(tmp_path: Path) -> None:
    first = tmp_path / "a.yaml"
    first.write_text("upsample:\n  ratio: 8\ntile:\n  overlap: 2.0\n")
    second = tmp_path / "b.yaml"
    second.write_text("upsample:\n  ratio: 16\n")
    config = load_config([first, second], {"tile.overlap": 3.0, "output.dir": None})
    assert config.upsample.ratio == 16
    assert config.tile.overlap == 3.0
    assert config.output.dir == Path("kitti-pu-out")  # None means "not given"


def test_unknown_key_is_rejected_with_its_dotted_name(tmp_path: Path) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text("tile:\n  patchsize: 128\n")
    with pytest.raises(ConfigError, match=r"tile\.patchsize: unknown key") as caught:
        load_config([path])
    assert str(path) in str(caught.value)


@pytest.mark.parametrize(
    ("overrides", "key"),
    [
        ({"upsample.ratio": 1}, "upsample.ratio"),
        ({"ground.method": "magic"}, "ground.method"),
        ({"output.formats": ["las"]}, "output.formats"),
        ({"input.first_frame": 5, "input.last_frame": 2}, "input.last_frame"),
        ({"upsample.device": "tpu"}, "upsample.device"),
    ],
)
def test_bad_values_name_their_key(overrides: dict, key: str) -> None:
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        load_config([], overrides)


def test_unknown_ground_parameter_is_rejected() -> None:
    with pytest.raises(ConfigError, match=r"ground\.params.*no_such_parameter"):
        load_config([], {"ground.params": {"no_such_parameter": 1.0}})


def test_ground_params_are_built_for_the_method() -> None:
    from stages import ground

    config = load_config([], {"ground.method": "patchwork"})
    assert isinstance(config.ground.method_params(), ground.params_class("patchwork"))


def test_missing_and_malformed_files_are_named(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="not found"):
        load_config([tmp_path / "absent.yaml"])
    broken = tmp_path / "broken.yaml"
    broken.write_text("tile: [unclosed\n")
    with pytest.raises(ConfigError, match="broken.yaml: not valid YAML at line 2, column 1") as info:
        load_config([broken])
    assert "\n" not in str(info.value)  # one line: the YAML error's own text ran over four
    with pytest.raises(ConfigError, match="is a folder, not a YAML file"):  # it said "not found"
        load_config([tmp_path])


def test_a_setting_or_section_given_twice_is_refused_naming_both_lines(tmp_path: Path) -> None:
    # YAML kept the last one silently: the first section's settings were lost without a word
    twice = tmp_path / "twice.yaml"
    twice.write_text("upsample:\n  seed: 3\ntile:\n  overlap: 1.0\nupsample:\n  ratio: 4\n")
    with pytest.raises(ConfigError, match=r"twice.yaml: not valid YAML at line 5, column 1 \(key 'upsample' "
                                          r"given twice \(first on line 1\)\)"):
        load_config([twice])
    twice.write_text("tile:\n  overlap: 1.0\n  overlap: 2.0\n")
    with pytest.raises(ConfigError, match=r"line 3, column 3 \(key 'overlap' given twice \(first on line 2\)\)"):
        load_config([twice])


def test_output_hash_follows_the_version_of_the_stages_output(monkeypatch: pytest.MonkeyPatch) -> None:
    before = load_config([], {}).output_hash()
    monkeypatch.setattr(config_module, "OUTPUT_VERSION", config_module.OUTPUT_VERSION + 1)
    assert load_config([], {}).output_hash() != before


def test_a_setting_added_off_leaves_the_output_hash_of_finished_runs_unchanged() -> None:
    # the default configuration's hash before snap.depth_edge_max_range existed (9781e99): finished
    # frames of a scheduled run stay finished across the upgrade, until the setting is used
    assert load_config([], {}).output_hash(legacy=True) == "0593c1e163f8f7bd"
    assert load_config([], {"snap.depth_edge_max_range": 20}).output_hash(legacy=True) != "0593c1e163f8f7bd"
    assert load_config([], {}).output_hash() == "1970137d4694df87"  # without the weights' name (below)
    # upsample.oversample came after that hash, off at 1
    assert load_config([], {"upsample.oversample": 1}).output_hash() == "1970137d4694df87"
    assert load_config([], {"upsample.oversample": 2}).output_hash() != "1970137d4694df87"
    # and so did upsample.offset_scale, off at 1
    assert load_config([], {"upsample.offset_scale": 1}).output_hash() == "1970137d4694df87"
    assert load_config([], {"upsample.offset_scale": 1.4}).output_hash() != "1970137d4694df87"
    dropped = load_config([], {"snap.depth_edges": "drop"}).output_hash()  # the limit changes nothing there
    assert load_config([], {"snap.depth_edges": "drop", "snap.depth_edge_max_range": 20}).output_hash() == dropped


def test_one_config_file_may_be_given_alone(tmp_path: Path) -> None:
    file = tmp_path / "c.yaml"
    file.write_text("tile:\n  overlap: 2.0\n")
    # a string was read as a list of files, one per character ("config file c: not found")
    assert load_config(str(file)).tile.overlap == load_config(file).tile.overlap == load_config([file]).tile.overlap == 2.0


def test_settings_that_give_the_same_points_hash_alike() -> None:
    # a copy of the weights elsewhere, or engine "eager" for "auto", redid every finished frame
    # ("config changed"): the model is compared by its checksum, and auto runs eager
    base = load_config([])
    assert base.output_hash() == load_config([], {"upsample.weights": "/elsewhere/copy.pt"}).output_hash()
    assert base.output_hash() == load_config([], {"upsample.engine": "eager"}).output_hash()
    assert base.output_hash() != load_config([], {"upsample.engine": "eager-bf16"}).output_hash()
    assert base.output_hash(legacy=True) != load_config([], {"upsample.engine": "eager"}).output_hash(legacy=True)


def test_output_hash_follows_output_relevant_settings_only() -> None:
    base = load_config([])
    assert base.output_hash() == load_config([], {"dask.n_workers": 7, "output.dir": "elsewhere"}).output_hash()
    assert base.output_hash() == load_config([], {"upsample.batch_size": 3}).output_hash()
    assert base.output_hash() != load_config([], {"upsample.ratio": 8}).output_hash()
    assert base.output_hash() != load_config([], {"tile.overlap": 2.5}).output_hash()
    assert base.output_hash() != load_config([], {"input.max_range": 100.0}).output_hash()
    assert base.output_hash() == load_config([], {"input.first_frame": 3}).output_hash()


def test_frame_range_is_inclusive_of_last_frame() -> None:
    config = load_config([], {"input.first_frame": 2, "input.last_frame": 6, "input.step": 2})
    assert list(config.input.frame_range()) == [2, 4, 6]
    assert load_config([]).input.frame_range() is None


def test_the_unordered_scans_preset_names_a_shipped_network_and_turns_snapping_off() -> None:
    from cadpu.weights import LIDAR_UNIFORM_WEIGHTS, resolve, sha256_of
    from pipeline.preflight import check_weights

    config = load_config([Path(__file__).parents[2] / "configs" / "unordered_scans.yaml"])
    assert resolve(config.upsample.weights) == LIDAR_UNIFORM_WEIGHTS
    assert not config.snap.enabled and not config.fill.enabled and config.upsample.max_patch_radius == 6.0
    assert check_weights(config) == sha256_of(LIDAR_UNIFORM_WEIGHTS)  # the file's bytes, not its sidecar


def test_a_key_of_an_earlier_version_names_its_new_place() -> None:
    with pytest.raises(ConfigError, match=r"stitch\.snap_to_rings: unknown key \(now snap\.enabled\)"):
        load_config([], {"stitch.snap_to_rings": False})


def test_sequence_names_that_yaml_reads_as_numbers_are_names(tmp_path: Path) -> None:
    settings = tmp_path / "seq.yaml"
    settings.write_text("input:\n  sequences: [00, 05]\n")  # YAML: the integers 0 and 5
    assert load_config([settings]).input.sequences == ["0", "5"]
    assert load_config(overrides={"input.sequences": 0}).input.sequences == ["0"]
    assert load_config(overrides={"input.sequences": "00"}).input.sequences == ["00"]


def test_a_minimum_range_at_or_beyond_the_maximum_is_refused() -> None:
    with pytest.raises(ConfigError, match=r"input.min_range \(300 m\) must be below input.max_range \(200 m\)"):
        load_config([], {"input.min_range": 300})  # every frame failed at load


def test_a_problem_names_the_file_that_holds_it_among_stacked_files(tmp_path: Path) -> None:
    bad, good = tmp_path / "bad.yaml", tmp_path / "good.yaml"
    bad.write_text("tile:\n  overlapp: 2.0\n")
    good.write_text("tile:\n  overlap: 1.5\n")
    with pytest.raises(ConfigError, match=rf"^bad configuration \({bad}\): tile.overlapp: unknown key "
                                          r"\(did you mean tile.overlap\?\)$"):
        load_config([bad, good])  # it named good.yaml, the last file read
    with pytest.raises(ConfigError, match=r"^bad configuration \(command-line options\): tile.overlap"):
        load_config([good], settings={"tile.overlap": "abc"})


def test_a_section_with_every_setting_commented_out_is_an_empty_section(tmp_path: Path) -> None:
    leftover = tmp_path / "leftover.yaml"
    leftover.write_text("tile:\n#  overlap: 2.0\nsnap:\n")
    assert load_config([leftover]) == load_config([])


def test_a_config_file_that_is_not_text_is_refused_naming_it(tmp_path: Path) -> None:
    file = tmp_path / "bin.yaml"
    file.write_bytes(b"\xff\xfe garbage")  # a UnicodeDecodeError traceback, exit 1, before
    with pytest.raises(ConfigError, match=f"config file {file}: not UTF-8 text"):
        load_config([file])


@pytest.mark.parametrize("key, value", [("snap.range_tolerance", "false"), ("upsample.oversample", "yes"),
                                        ("dask.n_workers", "true"), ("tile.overlap", "on")])
def test_true_and_false_are_refused_for_a_setting_that_is_not_a_switch(key: str, value: str) -> None:
    # taken as 0 and 1: range_tolerance=false, meant as off (null), set the strictest range check
    from pipeline.cli_common import _parse_sets  # --set's reader: YAML, where yes and on are true

    with pytest.raises(ConfigError, match=f"{key}: .* is not a value of this setting"):
        load_config([], {}, _parse_sets([f"{key}={value}"]))
    assert load_config([], {}, _parse_sets(["snap.range_tolerance=null", "dask.dashboard=true"])).snap.range_tolerance is None


def test_a_preset_is_found_by_name_from_any_folder(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from pipeline.config import presets

    # the snap stage's note says "-c configs/unordered_scans.yaml", which was "not found" outside
    # the repository's root (a new user's trial); the note now gives the name
    monkeypatch.chdir(tmp_path)
    shipped = load_config([Path(__file__).parents[2] / "configs" / "unordered_scans.yaml"])
    for given in ("unordered_scans", "unordered_scans.yaml", "configs/unordered_scans.yaml"):
        assert load_config([given]) == shipped, given
    assert "unordered_scans" in presets() and not any(name.startswith("train") for name in presets())
    assert "pipeline" not in presets()  # the defaults file: listed as a preset, it read as one that changes something
    with pytest.raises(ConfigError, match=r"config file nosuch: not found \(nor a preset; presets: .*unordered_scans"):
        load_config(["nosuch"])
    (tmp_path / "unordered_scans.yaml").write_text("snap:\n  enabled: true\n")  # a file of the name here wins
    assert load_config(["unordered_scans.yaml"]).snap.enabled


def test_a_misspelt_key_is_given_the_nearest_one_and_a_wrong_choice_what_was_given() -> None:
    # "tile.overlapp: unknown key" and "Input should be 'parquet', 'ply' or 'kitti'" alone (a new
    # user's trial)
    with pytest.raises(ConfigError, match=r"snap\.range_tolerence: unknown key \(did you mean snap\.range_tolerance\?\)"):
        load_config([], settings={"snap.range_tolerence": 0.1})
    with pytest.raises(ConfigError, match=r"snapp: unknown key \(did you mean snap\?\)"):
        load_config([], settings={"snapp.enabled": False})
    with pytest.raises(ConfigError, match=r"tile\.nonsense: unknown key$"):
        load_config([], settings={"tile.nonsense": 1})
    with pytest.raises(ConfigError, match=r"output.formats.0: Input should be 'parquet', 'ply' or 'kitti', got 'kitty'"):
        load_config([], settings={"output.formats": ["kitty"]})
    with pytest.raises(ConfigError, match=r"ground.method: Input should be .*, got 'ransc'"):
        load_config([], settings={"ground.method": "ransc"})
