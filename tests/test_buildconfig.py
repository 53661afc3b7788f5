"""The config a working directory remembers (depthgt.buildconfig): layers, refusals,
announced changes and how relative source roots resolve. No workflow run here
(test_cli runs the workflow with it)."""

from __future__ import annotations

import errno
from pathlib import Path

import pytest
import yaml

from depthgt.buildconfig import OVERRIDES, REMEMBERED, changed_keys, layered_config, merge, remember
from depthgt.errors import ConfigError, DepthGTError
from depthgt.settings import TOP_LEVEL_KEYS

BASE = {"seed": 3, "frameset": {"neighbours": 3, "stride": 2}, "sources": [{"name": "syn", "kind": "synthetic"}]}


def write(path: Path, doc: dict) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(doc))
    return path


@pytest.fixture
def wd(tmp_path) -> Path:
    """A working directory with its own config (the base layer)."""
    write(tmp_path / "wd" / "config" / "config.yaml", BASE)
    return tmp_path / "wd"


def test_merge_is_snakemakes():
    from snakemake.utils import update_config

    over = {"frameset": {"stride": 1}, "sources": [{"name": "b"}], "seed": 4}
    expected = yaml.safe_load(yaml.safe_dump(BASE))
    update_config(expected, over)
    assert merge(BASE, over) == expected
    assert BASE["frameset"] == {"neighbours": 3, "stride": 2}  # not changed in place


def test_changed_keys_takes_two_nans_for_the_same_value():
    assert changed_keys({"thr": float("nan"), "a": 1}, {"thr": float("nan"), "a": 1}) == []
    assert changed_keys({"thr": float("nan")}, {"thr": 0.5}) == ["thr: NaN -> 0.5"]


def test_changed_keys_names_each_key_with_both_values():
    new = merge(BASE, {"frameset": {"stride": 1}, "dataset": {"allow_empty": True}})
    assert changed_keys(BASE, new) == ["dataset.allow_empty: (unset) -> true", "frameset.stride: 2 -> 1"]
    moved = merge(BASE, {"sources": [{"name": "syn", "kind": "synthetic", "split": "test"}]})
    assert changed_keys(BASE, moved) == [
        'sources[syn]: {"kind": "synthetic", "name": "syn"} -> {"kind": "synthetic", "name": "syn", "split": "test"}'
    ]


def test_a_later_command_without_configfile_runs_with_the_builds(wd, tmp_path):
    mine = write(tmp_path / "mine.yaml", {"seed": 9, "frameset": {"stride": 1}})
    first = layered_config(wd, wd / "config/config.yaml", [mine])
    assert first.config["seed"] == 9 and first.config["frameset"] == {"neighbours": 3, "stride": 1}
    assert not first.changes  # nothing built yet: nothing to refuse
    remember(wd, first)
    assert yaml.safe_load((wd / OVERRIDES).read_text()) == {"seed": 9, "frameset": {"stride": 1}}
    assert yaml.safe_load((wd / REMEMBERED).read_text()) == first.config
    later = layered_config(wd, wd / "config/config.yaml")
    assert later.config == first.config and not later.changes and not later.base_changes
    again = layered_config(wd, wd / "config/config.yaml", [mine])  # the same file again: no change
    assert again.config == first.config and not again.changes
    assert remember(wd, again) == []  # nothing rewritten


def test_a_configfile_that_changes_a_build_is_refused_unless_reconfigure(wd, tmp_path, monkeypatch):
    remember(wd, layered_config(wd, wd / "config/config.yaml"))
    other = write(tmp_path / "other.yaml", {"seed": 5})
    monkeypatch.delenv("DEPTHGT_RECONFIGURE", raising=False)
    with pytest.raises(ConfigError) as err:
        layered_config(wd, wd / "config/config.yaml", [other])
    message = str(err.value)
    assert "seed: 3 -> 5" in message and "--reconfigure" in message and str(wd / OVERRIDES) in message
    applied = layered_config(wd, wd / "config/config.yaml", [other], reconfigure=True)
    assert applied.config["seed"] == 5 and applied.changes == ["seed: 3 -> 5"]
    monkeypatch.setenv("DEPTHGT_RECONFIGURE", "1")  # a plain Snakemake run's way
    assert layered_config(wd, wd / "config/config.yaml", [other]).config["seed"] == 5
    remember(wd, applied)
    monkeypatch.delenv("DEPTHGT_RECONFIGURE")
    assert layered_config(wd, wd / "config/config.yaml").config["seed"] == 5  # remembered from now on


def test_an_edit_of_the_working_directorys_config_is_applied_and_announced(wd):
    remember(wd, layered_config(wd, wd / "config/config.yaml"))
    write(wd / "config/config.yaml", merge(BASE, {"frameset": {"stride": 1}}))
    layers = layered_config(wd, wd / "config/config.yaml")
    assert layers.config["frameset"]["stride"] == 1 and not layers.changes
    assert layers.base_changes == ["frameset.stride: 2 -> 1"]
    assert "frameset.stride: 2 -> 1" in layers.notice() and str(wd / "config/config.yaml") in layers.notice()


def test_the_embedded_default_is_the_base_of_a_directory_without_config(tmp_path):
    default = write(tmp_path / "checkout" / "config" / "config.yaml", BASE)
    layers = layered_config(tmp_path / "empty", default)
    assert layers.base == default and layers.config == BASE


def test_relative_roots_resolve_against_the_configfiles_folder(tmp_path):
    data = tmp_path / "project" / "data" / "kitchen"
    data.mkdir(parents=True)
    mine = write(
        tmp_path / "project" / "configs" / "mine.yaml",
        {"sources": [{"name": "k", "kind": "sevenscenes", "root": "../data/kitchen", "scenes": "all"}]},
    )
    default = write(tmp_path / "checkout" / "config" / "config.yaml", BASE)
    layers = layered_config(tmp_path / "anywhere", default, [mine])
    assert layers.config["sources"][0]["root"] == str(data)  # absolute, whatever -d is
    # a root that does not exist is named with its absolute path and the rule
    bad = write(tmp_path / "project" / "configs" / "bad.yaml", {"sources": [{"name": "k", "root": "../nowhere"}]})
    with pytest.raises(ConfigError) as err:
        layered_config(tmp_path / "anywhere", default, [bad])
    assert str(err.value) == (
        f"config key sources[k].root: {tmp_path / 'project' / 'nowhere'} does not exist (../nowhere relative to "
        f"the folder of the config file that sets it, {tmp_path / 'project' / 'configs'})"
    )


def test_relative_roots_of_the_working_directorys_config_resolve_against_it(tmp_path):
    wd = tmp_path / "wd"
    write(wd / "config" / "config.yaml", {"sources": [{"name": "k", "root": "data/kitchen"}]})
    with pytest.raises(ConfigError) as err:
        layered_config(wd, wd / "config/config.yaml")
    assert str(err.value) == (
        f"config key sources[k].root: {wd / 'data/kitchen'} does not exist (data/kitchen relative to the working "
        f"directory {wd})"
    )
    (wd / "data" / "kitchen").mkdir(parents=True)
    assert layered_config(wd, wd / "config/config.yaml").config["sources"][0]["root"] == "data/kitchen"


def test_a_config_file_that_does_not_parse_is_named_with_its_line(wd, tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("seed: 0\nframeset: {neighbours: [3\n")
    with pytest.raises(ConfigError, match=rf"--configfile {bad}:3:1: not valid YAML"):
        layered_config(wd, wd / "config/config.yaml", [bad])
    (tmp_path / "list.yaml").write_text("- 1\n")
    with pytest.raises(ConfigError, match="must hold a mapping of config keys, got list"):
        layered_config(wd, wd / "config/config.yaml", [tmp_path / "list.yaml"])
    (tmp_path / "tabs.json").write_text('{\n\t"seed": 1\n}')  # JSON as Snakemake reads it
    assert layered_config(wd, wd / "config/config.yaml", [tmp_path / "tabs.json"]).config["seed"] == 1


def test_the_reports_refusal_says_what_works_for_the_report(wd, tmp_path, monkeypatch):
    """depthgt report has no --reconfigure: its refusal does not offer one, but the
    build command that applies the change (with this command's files) and leaving
    --configfile out."""
    remember(wd, layered_config(wd, wd / "config/config.yaml"))
    other = write(tmp_path / "my configs" / "other.yaml", {"seed": 5})
    monkeypatch.setenv("DEPTHGT_RECONFIGURE", "1")  # not read by the report: it cannot apply a change
    with pytest.raises(ConfigError) as err:
        layered_config(wd, wd / "config/config.yaml", [other], reconfigure=False, command="report")
    message = str(err.value)
    assert "\n" not in message and "seed: 3 -> 5" in message and str(wd / OVERRIDES) in message
    assert "depthgt report shows the build as it was made and takes no --reconfigure" in message
    assert f"depthgt build -d {wd} --reconfigure --configfile '{other}'" in message  # quoted: a space
    assert "leave --configfile out" in message and "pass --reconfigure" not in message
    assert "DEPTHGT_RECONFIGURE" not in message
    # a build's refusal is as before
    with pytest.raises(ConfigError, match="pass --reconfigure to apply the change"):
        layered_config(wd, wd / "config/config.yaml", [other], reconfigure=False)


def test_a_configfile_with_unknown_keys_is_named_and_a_target_read_as_one_said_so(wd, tmp_path):
    """`snakemake --configfile mine.yaml results/.../index.json`: Snakemake reads the
    target, an existing JSON mapping, as a second config file; refused in one line naming
    it, its keys and where targets go (the index has a key `dataset`, a config key too). A
    file with a typo is named with the key, without the hint."""
    index = wd / "results" / "scenes" / "syn" / "room_000" / "index.json"
    index.parent.mkdir(parents=True)
    index.write_text('{"dataset": "syn", "scene": "room_000", "frames": [0, 1], "n_frames": 2}')
    mine = write(tmp_path / "mine.yaml", {"seed": 5})
    with pytest.raises(ConfigError) as err:
        layered_config(wd, wd / "config/config.yaml", [mine, index], config_keys=TOP_LEVEL_KEYS)
    message = str(err.value)
    assert "\n" not in message and message.startswith(
        f"--configfile {index}: unknown config key(s) scene, frames, n_frames (allowed: dataset, device, enhance,"
    )
    assert message.endswith(
        "Is it a target? Snakemake reads every value after --configfile, up to the next option, as a config file: "
        "write targets before --configfile (snakemake TARGET ... --configfile FILE)"
    )
    typo = write(tmp_path / "typo.yaml", {"seed": 5, "sed": 4})
    with pytest.raises(ConfigError) as err:
        layered_config(wd, wd / "config/config.yaml", [typo], config_keys=TOP_LEVEL_KEYS)
    assert str(err.value).startswith(f"--configfile {typo}: unknown config key(s) sed (allowed: ")
    assert "target" not in str(err.value)
    assert layered_config(wd, wd / "config/config.yaml", [mine], config_keys=TOP_LEVEL_KEYS).config["seed"] == 5
    assert layered_config(wd, wd / "config/config.yaml", [index]).config["frames"] == [0, 1]  # not checked


def test_a_full_disk_while_remembering_is_one_line_and_leaves_no_temporary_file(wd, tmp_path, monkeypatch):
    remember(wd, layered_config(wd, wd / "config/config.yaml"))
    before = {p.name: p.read_text() for p in (wd / "results/config").iterdir()}
    changed = layered_config(wd, wd / "config/config.yaml", [write(tmp_path / "o.yaml", {"seed": 5})], reconfigure=True)

    def half_then_enospc(self, text, *args, **kwargs):
        with open(self, "w", encoding="utf-8") as fh:
            fh.write(text[: len(text) // 2])
        raise OSError(errno.ENOSPC, "No space left on device", str(self))

    monkeypatch.setattr(Path, "write_text", half_then_enospc)
    with pytest.raises(DepthGTError) as err:
        remember(wd, changed)
    monkeypatch.undo()
    message = str(err.value)
    assert "\n" not in message and message.startswith(
        f"cannot remember the run's config in {wd / OVERRIDES}: No space left on device ("
    )
    assert "MB free on its file system); free space and run again" in message
    after = {p.name: p.read_text() for p in (wd / "results/config").iterdir()}
    assert after == before  # no temporary file; the remembered config as it was


def test_a_config_folder_that_cannot_be_made_is_named_in_one_line(wd):
    (wd / "results").mkdir()
    (wd / "results" / "config").write_text("")  # a file where the folder goes
    with pytest.raises(DepthGTError) as err:
        remember(wd, layered_config(wd, wd / "config/config.yaml"))
    assert str(err.value).startswith(
        f"cannot remember the run's config in {wd / OVERRIDES}: File exists: {wd / 'results/config'} ("
    )
    assert str(err.value).endswith("; fix that and run again")
