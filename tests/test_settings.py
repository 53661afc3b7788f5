"""The settings: torch-free, one builder, every section checked with the key named, and
every enum and default written once (the dataclasses are the one check of a config)."""

from __future__ import annotations

import ast
import dataclasses
import json
import re
import subprocess
import sys
import typing
from pathlib import Path

import pytest
import yaml

from depthgt.errors import ConfigError
from depthgt.settings import (
    REGISTRATION_KEYS,
    REGISTRATION_PRESETS,
    FrameSetSettings,
    RegistrationSettings,
    Settings,
    TrainSettings,
    check_workflow,
    config_with_defaults,
    registration_settings,
    settings_from_config,
)
from depthgt.settings_base import choices

REPO = Path(__file__).resolve().parents[1]


def test_importing_settings_does_not_import_torch():
    """The builder imports every stage's settings module, each beside its stage: also
    those inside packages whose modules import torch (depthgt.registration,
    depthgt.gt.render), whose names load on first use (depthgt.lazy)."""
    code = "import depthgt.settings, depthgt.registry, sys; assert 'torch' not in sys.modules, sorted(sys.modules)"
    subprocess.run([sys.executable, "-c", code], check=True)
    code = (
        "import importlib; module = importlib.import_module('depthgt.registration.align'); "
        "from depthgt.registration import METHODS, align; assert align is module.align and 'given' in METHODS"
    )
    subprocess.run([sys.executable, "-c", code], check=True)  # a name stays the name when its submodule loads first


def test_default_config_builds_every_stage():
    config = yaml.safe_load((REPO / "config/config.yaml").read_text())
    s = settings_from_config(config)
    assert isinstance(s, Settings) and s.size_hw == (256, 256)
    assert s.frameset == FrameSetSettings(neighbours=3, stride=2, target_step=2)
    assert (
        s.registration.method == "given"
        and s.registration.preset == "paper"
        and s.registration.encoder.precision == "auto"
    )
    assert [src.name for src in s.sources] == ["synthetic", "synthetic_test"]
    # every trainable model of the registry has its training settings; RDE trains LapDEN with LapDEN's entry
    assert set(s.enhance.models) == {"lapden", "ddrnet", "sdd", "rde"}
    assert s.train("rde").model == "lapden" and s.train("rde").epochs == s.train("lapden").epochs == 30
    assert s.train("ddrnet").model_params == {"channels": 8} and s.train("ddrnet").batch_size == 8
    assert s.train("sdd").progress is False and s.train("sdd").seed == 0
    assert s.enhance.rde.backend == "torch" and s.evaluation.models == ["ddrnet", "sdd", "rde", "lapden"]


def _merged(base: dict, preset: dict) -> dict:
    """``preset`` over ``base`` as Snakemake merges a --configfile: mappings key by key,
    anything else (lists: the sources) replaced."""
    out = dict(base)
    for k, v in preset.items():
        out[k] = _merged(base[k], v) if isinstance(v, dict) and isinstance(base.get(k), dict) else v
    return out


def test_presets_validate():
    """Every preset over the default config passes the workflow's checks and builds every
    stage; the paper profile has the paper's sizes, Table 2's preset one real recording
    per split."""
    base = yaml.safe_load((REPO / "config/config.yaml").read_text())
    built = {}
    for path in sorted((REPO / "config/presets").glob("*.yaml")):
        config = _merged(base, yaml.safe_load(path.read_text()))
        check_workflow(settings_from_config(config))
        built[path.stem] = settings_from_config(config_with_defaults(config))
        assert built[path.stem] == settings_from_config(config)
    paper = built["paper"]
    assert paper.train("lapden").model_params == {"preset": "paper"} and paper.train("rde").model_params == {
        "preset": "paper"
    }
    assert all(paper.train(m).epochs == 100 for m in ("lapden", "ddrnet", "sdd", "rde"))
    train_rooms = next(src for src in paper.sources if src.name == "synthetic")
    planned = len(train_rooms.scenes) * len(paper.frameset.targets(train_rooms.options["n_frames"]))
    assert 2900 <= planned <= 3100  # the paper's ~3,000 frame sets
    real = built["table2-real"]
    assert {src.name: (src.kind, src.split) for src in real.sources} == {
        "tum": ("tum", "auto"),
        "kitchen": ("sevenscenes", "test"),
    }
    assert real.registration.method == "refine"


def test_paper_preset_plans(tmp_path):
    """The GPU profile plans (dry run, nothing built, no GPU needed to plan): every
    frame-set batch of its 60 rooms, the four models, the seven methods."""
    import shutil

    from conftest import snakemake

    shutil.copytree(REPO / "config", tmp_path / "config")
    proc = snakemake(tmp_path, "-n", "--configfile", str(tmp_path / "config/presets/paper.yaml"))
    stats = dict(line.split()[:2] for line in proc.stdout.split("Job stats:")[1].splitlines()[3:15] if line.strip())
    assert stats["scene_index"] == "60" and stats["train_model"] == "4" and stats["evaluate_method"] == "7"
    assert int(stats["frameset_batch"]) >= 96  # 48 rooms x 2 batches of 32, 12 test rooms x 1 (108 planned)


def test_training_threads_follow_the_cores(tmp_path):
    """train_model asks for a quarter of --cores, one thread at least and two at most:
    on 2 cores two trainings run side by side on one thread each; the SLURM profile sets
    two (dry runs of the default config's trainings)."""
    import re
    import shutil

    from conftest import snakemake

    shutil.copytree(REPO / "config", tmp_path / "config")

    def threads(cores: str, *args: str) -> list[int]:
        proc = snakemake(tmp_path, "-n", "train", "--cores", cores, *args)
        text = proc.stdout + proc.stderr
        jobs = [j for j in text.split("\n\n") if "rule train_model:" in j]
        return [int(m.group(1)) if (m := re.search(r"threads: (\d+)", j)) else 1 for j in jobs]

    assert threads("2") == [1] * 4 and threads("8") == [2] * 4
    # on a cluster each training is a job of its own: the SLURM profile gives it two threads
    assert threads("2", "--profile", str(REPO / "profiles/slurm")) == [2] * 4


def test_missing_sections_take_defaults():
    s = settings_from_config({})
    assert s.patches.count == 6 and s.render.m == 64 and s.registration.refine_settings.iters == (10, 8, 6)


@pytest.mark.parametrize(
    "config, key",
    [
        ({"bogus": 1}, "bogus"),
        ({"patches": {"cuont": 6}}, "patches.cuont"),
        ({"render": {"radius": 1.0}}, "render.radius"),
        ({"registration": {"method": "given", "n_blocs": 2}}, "registration.n_blocs"),  # checked whatever the method
        ({"registration": {"refine_settings": {"iter": [1]}}}, "registration.refine_settings.iter"),
        ({"registration": {"pretrain": {"epoch": 1}}}, "registration.pretrain.epoch"),
        ({"enhance": {"train": {"epoch": 3}}}, "epoch"),
        ({"enhance": {"models": {"unet": {}}}}, "enhance.models.unet"),
        ({"enhance": {"rde": {"voxel": 0.02}}}, "enhance.rde.voxel"),
        ({"evaluation": {"method": ["input"]}}, "evaluation.method"),
        ({"sources": [{"name": "a", "kind": "synthetic", "scene": ["x"]}]}, "sources[0].scene"),
    ],
)
def test_unknown_keys_are_named(config, key):
    with pytest.raises(ConfigError, match="unknown config key") as err:
        settings_from_config(config)
    assert key in str(err.value)


@pytest.mark.parametrize(
    "config, key",
    [
        ({"patches": {"size": 300}}, "patches.size"),  # larger than resize (256)
        ({"resize": 128, "patches": {"size": 129}}, "patches.size"),
        ({"patches": {"count": 100_000}}, "patches.count"),  # memory bound
        ({"resize": 100_000}, "resize"),
        ({"frameset": {"neighbours": 500}}, "frameset.neighbours"),
        ({"render": {"m": 0}}, "render.m"),
        ({"render": {"edge_vote": 1.5}}, "render.edge_vote"),
        ({"render": {"edge_vote_slack_px": -0.5}}, "render.edge_vote_slack_px"),
        ({"render": {"leave_target_out_stride": 0}}, "render.leave_target_out_stride"),
        ({"render": {"target_resolves_ambiguous": "yes"}}, "render.target_resolves_ambiguous"),  # wrong type
        ({"registration": {"n_candidates": 10**7}}, "registration.n_candidates"),
        ({"registration": {"method": "given", "pairs": "some"}}, "registration.pairs"),
        ({"registration": {"preset": "slow"}}, "registration.preset"),
        ({"registration": {"on_failure": "keep"}}, "registration.on_failure"),
        ({"patches": {"count": "6"}}, "patches.count"),  # wrong type
        ({"device": "tpu"}, "device"),
        ({"enhance": {"train": {"epochs": 0}}}, "train.epochs"),
        ({"enhance": {"models": {"sdd": {"model": "lapden"}}}}, "enhance.models.sdd.model"),
        ({"evaluation": {"methods": ["input", "bilateral"]}}, "evaluation.methods"),
        ({"sources": [{"name": "a", "kind": "kinect"}]}, "kind"),
        ({"sources": [{"name": "a", "kind": "synthetic", "scenes": ["../x"]}]}, "scenes"),
        ({"sources": [{"name": "a", "kind": "synthetic"}, {"name": "a", "kind": "synthetic"}]}, "sources"),
    ],
)
def test_bad_values_name_the_key(config, key):
    with pytest.raises(ConfigError, match="config key") as err:
        settings_from_config(config)
    assert key in str(err.value)


def test_registration_presets_and_types():
    fast = settings_from_config({"registration": {"method": "overfit", "preset": "fast", "iterations": 2}}).registration
    assert isinstance(fast, RegistrationSettings)
    assert (fast.encoder.channels, fast.training.iterations, fast.refine_settings.iters) == (32, 2, (8, 5, 3))
    assert fast.pretrain.framesets == 16
    # numbers given as ints where floats are expected are accepted and stored as floats
    s = settings_from_config({"render": {"radius_px": 2}, "enhance": {"rde": {"trunc_voxels": 4}}})
    assert (
        isinstance(s.render.radius_px, float)
        and s.render.radius_px == 2.0
        and isinstance(s.enhance.rde.trunc_voxels, float)
    )


def test_nested_sections_and_lists_of_the_wrong_type_are_named():
    for refine, key, what in (
        ("abc", "registration.refine_settings", "must be a mapping, got str 'abc'"),
        ([1], "registration.refine_settings", "must be a mapping, got list [1]"),
        ({"iters": "abc"}, "registration.refine_settings.iters", "must be a list, got str 'abc'"),
        (
            {"max_dist_m": ["x", 0.1, 0.1]},
            r"registration.refine_settings.max_dist_m\[0\]",
            "must be float, got str 'x'",
        ),
    ):
        with pytest.raises(ConfigError, match=f"{key}: " + re.escape(what)):
            settings_from_config({"registration": {"method": "refine", "refine_settings": refine}})
    ok = settings_from_config({"registration": {"method": "refine", "refine_settings": {"max_dist_m": [1, 0.5, 0.2]}}})
    assert ok.registration.refine_settings.max_dist_m == (1, 0.5, 0.2)


def test_a_number_yaml_read_as_text_is_named_with_how_to_write_it():
    # YAML 1.1 (PyYAML, Snakemake's --configfile) reads 1e-4, without a dot, as a string
    config = yaml.safe_load(
        "registration: {method: refine, refine_settings: {damping: 1e-4, max_dist_m: [1e-1, 0.05, 0.03]}}"
    )
    assert config["registration"]["refine_settings"]["damping"] == "1e-4"  # the trap itself
    with pytest.raises(ConfigError, match=r"refine_settings.damping: must be float, got str '1e-4' .*write 0\.0001"):
        settings_from_config(config)
    config["registration"]["refine_settings"]["damping"] = 1e-4
    with pytest.raises(ConfigError, match=r"max_dist_m\[0\]: must be float, got str '1e-1' .*write 0\.1"):
        settings_from_config(config)
    with pytest.raises(ConfigError, match=r"must be float, got str 'abc'$"):
        settings_from_config({"registration": {"method": "refine", "refine_settings": {"damping": "abc"}}})


def test_shared_training_settings_are_checked_where_every_model_overrides_them():
    models = {m: {"epochs": 3} for m in ("lapden", "ddrnet", "sdd")}
    for value, what in (("ten", "must be int, got str 'ten'"), (2.5, "must be int, got float 2.5")):
        with pytest.raises(ConfigError, match=f"enhance.train.epochs: {what}"):
            settings_from_config({"enhance": {"train": {"epochs": value}, "models": models}})
    with pytest.raises(ConfigError, match="enhance.train.epochs: must be >= 1, got -3"):
        settings_from_config({"enhance": {"train": {"epochs": -3}, "models": models}})
    # a check across keys whose other key comes from each model's entry is the merged entries' to make
    split = {m: {"input_hole_max_px": 32} for m in ("lapden", "ddrnet", "sdd")}
    s = settings_from_config({"enhance": {"train": {"input_hole_min_px": 20}, "models": split}})
    assert s.enhance.models["lapden"].input_hole_min_px == 20 and s.enhance.models["rde"].input_hole_max_px == 32


def test_train_settings_identity_ignores_epochs():
    a, b = TrainSettings(epochs=3), TrainSettings(epochs=5)
    assert a.identity() == b.identity() and TrainSettings(lr=1e-4).identity() != a.identity()
    # a constant-rate identity has no schedule key: checkpoints from before it existed resume
    assert "lr_schedule" not in a.identity() and "epochs" not in a.identity()
    # with the cosine schedule the rate of every step depends on the epochs: a longer run is another run
    c3, c5 = TrainSettings(epochs=3, lr_schedule="cosine"), TrainSettings(epochs=5, lr_schedule="cosine")
    assert c3.identity() != c5.identity() and c3.identity() != a.identity()
    assert c3.identity() == TrainSettings(epochs=3, lr_schedule="cosine", progress=False).identity()


def test_train_settings_input_holes_are_checked_and_in_the_identity_only_when_cut():
    plain = TrainSettings()
    assert not {"input_holes", "input_hole_min_px", "input_hole_max_px"} & set(plain.identity())
    assert TrainSettings(input_hole_max_px=30).identity() == plain.identity()  # radii of no holes
    cut = TrainSettings(input_holes=4)
    assert (
        cut.identity()["input_holes"] == 4
        and cut.identity() != TrainSettings(input_holes=4, input_hole_max_px=30).identity()
    )
    with pytest.raises(ConfigError, match="train.input_holes.*0..64.*-1"):
        TrainSettings(input_holes=-1)
    with pytest.raises(ConfigError, match="input_hole_min_px/input_hole_max_px.*9, 5"):
        TrainSettings(input_holes=2, input_hole_min_px=9, input_hole_max_px=5)
    s = settings_from_config({"enhance": {"train": {"input_holes": 3}}})
    assert s.train("lapden").input_holes == 3 and s.train("rde").input_holes == 3


def test_train_settings_lr_schedule_is_checked():
    with pytest.raises(ConfigError, match="lr_schedule.*constant, cosine.*'step'"):
        TrainSettings(lr_schedule="step")
    s = settings_from_config({"enhance": {"train": {"lr_schedule": "cosine"}, "models": {"sdd": {"epochs": 12}}}})
    assert s.train("sdd").lr_schedule == "cosine" and s.train("sdd").epochs == 12


def test_every_section_with_a_problem_is_named_at_once():
    """One error names its key alone; problems in several sections are listed together
    (each section's first), as the JSON schema's check listed them before."""
    config = yaml.safe_load((REPO / "config/config.yaml").read_text())
    with pytest.raises(ConfigError, match=r"^config key patches.filter_on: must be one of gt, input, both, got 'rgb'$"):
        settings_from_config({**config, "patches": {"filter_on": "rgb"}})
    bad = {**config, "bogus": 1, "device": "tpu", "patches": {"filter_on": "rgb"}, "render": {"plane": "curved"}}
    with pytest.raises(ConfigError) as err:
        settings_from_config(bad)
    lines = str(err.value).splitlines()
    assert lines[0] == "invalid configuration:" and len(lines) == 5
    for key in (
        "unknown config key(s) bogus",
        "device: must be one of auto, cpu, cuda",
        "patches.filter_on",
        "render.plane",
    ):
        assert sum(key in line for line in lines) == 1, (key, lines)
    # what the JSON schema required: a source, each with a name and a kind
    with pytest.raises(ConfigError, match="config key sources: the workflow builds from at least one source"):
        check_workflow(settings_from_config({}))
    with pytest.raises(ConfigError, match=r"config key sources\[0\]\.kind: required"):
        settings_from_config({"sources": [{"name": "a"}]})
    for section in ("enhance", "registration", "frameset"):
        with pytest.raises(ConfigError, match=f"config key {section}: must be a mapping, got int 5"):
            settings_from_config({section: 5})
    with pytest.raises(ConfigError, match="config key enhance.models.sdd: must be a mapping, got list"):
        settings_from_config({"enhance": {"models": {"sdd": [1]}}})


def test_settings_doc_is_json_ready():
    doc = settings_from_config({}).doc("frameset", "registration")
    assert doc["frameset"] == {
        "neighbours": 3,
        "stride": 2,
        "target_step": 1,
        "batch_size": 32,
        "selection": "window",
        "coverage_span": 30,
        "coverage_views": 4,
        "coverage_max_baseline_m": 0.3,
        "coverage_max_angle_deg": 20.0,
        "coverage_min_fill_px": 50,
        "coverage_mixed_margin_px": 1,
        "coverage_mixed_jump_rel": 0.03,
    }
    assert doc["registration"]["refine_settings"]["scales"] == [4, 2, 1]


def test_registration_parts_keep_the_flat_config_keys():
    """RegistrationSettings holds the parts each step reads (encoder, matching, training,
    checks); the config section stays flat: every key lands in exactly one place, and the
    section round-trips (as_config -> from_keys) for the default and every preset."""
    top = {f.name for f in dataclasses.fields(RegistrationSettings)}
    parts = [
        {f.name for f in dataclasses.fields(type(getattr(RegistrationSettings(), p)))}
        for p in ("encoder", "matching", "training", "checks")
    ]
    places = [k for k in REGISTRATION_KEYS for names in [top, *parts] if k in names]
    assert sorted(places) == sorted(REGISTRATION_KEYS)  # each key in exactly one place
    for preset in (None, *REGISTRATION_PRESETS):
        s = registration_settings({} if preset is None else {"preset": preset, "method": "overfit"})
        assert list(s.as_config()) == list(REGISTRATION_KEYS)
        assert RegistrationSettings.from_keys(s.as_config()) == s
    s = registration_settings({"top_k": 50, "max_residual_m": 0.01, "precision": "bf16", "lr": 0.5})
    assert (s.matching.top_k, s.checks.max_residual_m, s.encoder.precision, s.training.lr) == (50, 0.01, "bf16", 0.5)
    assert s.with_keys(min_ok_fraction=0.25).checks.min_ok_fraction == 0.25
    assert s.with_keys(min_ok_fraction=0.25).matching == s.matching
    with pytest.raises(ConfigError, match="registration.top_k"):
        s.with_keys(top_k=2)
    with pytest.raises(ConfigError, match="registration.encoder"):  # the parts are not config keys
        registration_settings({"encoder": {"n_blocks": 1}})


def test_the_workflow_writes_the_settings_defaults_into_its_config():
    """The workflow writes the defaults of WRITTEN_DEFAULTS into its config (the rules'
    params, the source entries index.json and the card record): the values the settings
    give, the config's own keys kept where they are; the result builds the same settings
    and the config itself is not changed. Every path and key of the table is a section
    and a key of the settings (a renamed field fails here)."""
    from depthgt.settings import SECTIONS, WRITTEN_DEFAULTS, SourceSettings, SplitSettings

    bare = {"sources": [{"name": "s", "kind": "synthetic"}], "split": {"block_frames": 9}}
    before = json.dumps(bare)
    filled = config_with_defaults(bare)
    assert json.dumps(bare) == before
    assert settings_from_config(filled) == settings_from_config(bare)
    assert list(filled) == ["sources", "split", *(k for k in WRITTEN_DEFAULTS[""] if k != "split")]
    assert filled["split"] == {"block_frames": 9, "val_fraction": SplitSettings().val_fraction}
    assert list(filled["sources"][0]) == ["name", "kind", "root", "scenes", "split", "options"]
    assert filled["registration"]["preset"] == registration_settings({}).preset == "paper"
    assert filled["render"] == {} and filled["enhance"]["train"] == {} and "methods" not in filled["evaluation"]
    doc = settings_from_config({}).doc(*WRITTEN_DEFAULTS[""])
    source_fields = {f.name: f for f in dataclasses.fields(SourceSettings)}
    for key in WRITTEN_DEFAULTS["sources[]"]:
        f = source_fields[key]
        assert filled["sources"][0][key] == (f.default_factory() if f.default is dataclasses.MISSING else f.default)
    for path, keys in WRITTEN_DEFAULTS.items():
        if path == "sources[]":
            continue
        assert path == "" or path.split(".")[0] in SECTIONS, path
        node, section = doc, config_with_defaults({})
        for part in path.split(".") if path else []:
            node, section = node.get(part, {}), section[part]
        for key in keys:
            if (f"{path}.{key}" if path else key) not in WRITTEN_DEFAULTS:
                assert section[key] == node[key] and type(section[key]) is type(node[key]), (path, key)


def _settings_classes(cls: type, found: dict[str, type]) -> dict[str, type]:
    """Every settings dataclass reachable from ``cls``'s fields, by name."""
    found[cls.__name__] = cls
    for hint in typing.get_type_hints(cls).values():
        for option in typing.get_args(hint) or (hint,):
            for inner in typing.get_args(option) or (option,):
                if dataclasses.is_dataclass(inner) and inner.__name__ not in found:
                    _settings_classes(inner, found)
    return found


#: ``.get(key, default)`` fallbacks on a config key that repeat its settings default, still
#: there, each with why (the list only shrinks: test_no_enum_or_default_is_written_twice
#: fails when one is gone).
KNOWN_REPEATED_DEFAULTS = {
    # the index job reads the source entry its rule passes (the workflow wrote split in);
    # its module is being rewritten (issue 43 item 4)
    ("src/depthgt/jobs/gt.py", "split", "auto"),
    # library callers (tests) pass source entries without the workflow's defaults
    ("src/depthgt/sources/base.py", "split", "auto"),
}

_QUOTED = re.compile(r"""[(\[{]\s*((?:["'][^"'\n]*["']\s*,\s*)+["'][^"'\n]*["'])\s*,?\s*[)\]}]""")
_GET = re.compile(r"""\.(?:get|pop|setdefault)\(\s*["'](\w+)["']\s*,\s*([^)]+)\)""")


def _rule_files(repo: Path) -> list[Path]:
    return [repo / "Snakefile", *sorted((repo / "workflow").rglob("*.smk"))]


def _written_twice(repo: Path) -> tuple[list[str], set[tuple]]:
    """Where ``repo``'s code (src/depthgt, workflow/*.py) and rules (Snakefile,
    workflow/*.smk) write a settings enum or default again: (the places, the repeated
    defaults found)."""
    enums, defaults = {}, {}
    for cls in _settings_classes(Settings, {}).values():
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            if len(choices(hints[f.name])) >= 2:
                enums[f"{cls.__name__}.{f.name}"] = set(choices(hints[f.name]))
            if isinstance(f.default, (str, int, float, bool)):
                defaults.setdefault(f.name, []).append(f.default)
    assert {"RenderSettings.plane", "PatchSettings.filter_on", "RegistrationSettings.on_failure"} <= set(enums)
    repeated, found = [], set()
    for path in sorted((repo / "src/depthgt").rglob("*.py")) + sorted((repo / "workflow").rglob("*.py")):
        tree = ast.parse(path.read_text())
        declared = {
            id(n.slice)
            for n in ast.walk(tree)
            if isinstance(n, ast.Subscript) and getattr(n.value, "id", "") == "Literal"
        }
        for node in ast.walk(tree):
            if isinstance(node, (ast.Tuple, ast.List, ast.Set)) and id(node) not in declared:
                values = {e.value for e in node.elts if isinstance(e, ast.Constant) and isinstance(e.value, str)}
                where = f"{path.relative_to(repo)}:{node.lineno}"
                repeated += [f"{where}: {name}" for name, c in enums.items() if c <= values]
            if isinstance(node, ast.Call) and getattr(node.func, "attr", "") in ("get", "pop", "setdefault"):
                if len(node.args) == 2 and all(isinstance(a, ast.Constant) for a in node.args):
                    key, value = (a.value for a in node.args)
                    if any(type(d) is type(value) and d == value for d in defaults.get(key, ())):
                        entry = (str(path.relative_to(repo)), key, value)
                        found.add(entry)
                        if entry not in KNOWN_REPEATED_DEFAULTS:
                            repeated.append(f"{entry[0]}:{node.lineno}: {key!r} falls back to its default {value!r}")
    for path in _rule_files(repo):
        text = path.read_text()
        for m in _QUOTED.finditer(text):
            values = set(re.findall(r"""["']([^"']*)["']""", m.group(1)))
            repeated += [f"{path.relative_to(repo)}: {m.group(0)}: {name}" for name, c in enums.items() if c <= values]
        for key, value in _GET.findall(text):
            if key in defaults:
                repeated.append(f"{path.relative_to(repo)}: .get({key!r}, {value.strip()}): a default of the settings")
    return repeated, found


def test_no_enum_or_default_is_written_twice():
    """The settings dataclasses are the one check of a config (no JSON schema beside
    them, no Snakemake validate), each enum is written once, as its field's ``Literal``
    type, and each default once, as its field's default: no tuple, list or set of the
    code or the rules lists every choice of an enum again, and nothing reads a config key
    with its settings default as the fallback (``source.get("split", "auto")``)."""
    assert not [p for p in (REPO / "workflow").rglob("*") if "schema" in p.name], "a config schema beside the settings"
    assert "validate(" not in "".join(p.read_text() for p in (REPO / "workflow/rules").glob("*.smk"))
    repeated, found = _written_twice(REPO)
    assert not repeated, "enums or defaults written again:\n" + "\n".join(repeated)
    gone = KNOWN_REPEATED_DEFAULTS - found
    assert not gone, f"no longer repeated: delete from KNOWN_REPEATED_DEFAULTS: {sorted(gone)}"


def test_the_check_for_repeated_enums_and_defaults_sees_them(tmp_path):
    """_written_twice finds a tuple of an enum's choices and a fallback with a settings
    default, in code and in the rules."""
    code, rules = tmp_path / "src" / "depthgt", tmp_path / "workflow" / "rules"  # not paths of this repository
    code.mkdir(parents=True)
    rules.mkdir(parents=True)
    (tmp_path / "Snakefile").write_text("")
    (code / "fake.py").write_text('PLANES = ("none", "fit", "normals", "other")\nx = c.get("stride", 2)\n')
    (rules / "fake.smk").write_text('if c.get("filter_on", "gt") in ["gt", "input", "both"]:\n')
    text = "\n".join(_written_twice(tmp_path)[0])
    assert "fake.py:1: RenderSettings.plane" in text and "fake.py:2: 'stride' falls back to its default 2" in text
    assert "PatchSettings.filter_on" in text and """.get('filter_on', "gt"): a default""" in text


def test_overfit_without_a_train_split_fails_when_the_workflow_starts(tmp_path):
    """Issue 18 item 5: the encoder's pretraining needs frame sets of the train split;
    without a source that gives any, the run stops before its first job (a dry run
    shows it) with the keys to change, not in the pretraining job."""
    from conftest import make_workdir, snakemake

    from depthgt.settings import check_workflow

    test_only = {
        "registration": {"method": "overfit", "preset": "fast"},
        "sources": [
            {
                "name": "t",
                "kind": "synthetic",
                "scenes": ["room_000"],
                "split": "test",
                "options": {"n_frames": 8, "width": 80, "height": 60},
            }
        ],
    }
    with pytest.raises(ConfigError, match=r"registration.pretrain.framesets: 16 .*sources\[0\].split: test"):
        check_workflow(settings_from_config(test_only))
    # fine: pretraining off, a train or auto source, or the given poses
    check_workflow(
        settings_from_config({**test_only, "registration": {"method": "overfit", "pretrain": {"framesets": 0}}})
    )
    check_workflow(settings_from_config({**test_only, "sources": [dict(test_only["sources"][0], split="auto")]}))
    check_workflow(settings_from_config({**test_only, "registration": {"method": "given"}}))

    wd = make_workdir(tmp_path / "wd", test_only)
    proc = snakemake(wd, "-n", check=False)
    assert proc.returncode != 0
    text = proc.stdout + proc.stderr
    assert "registration.pretrain.framesets" in text and "sources[0].split: test" in text, text[-2000:]
    assert not (wd / "results").exists()


# --------------------------------------------------------------------------- the stages' config sections


def _validated(*extra: Path) -> dict:
    """config/config.yaml with ``extra`` merged over it, checked and its defaults written
    in, as the workflow builds the run's config (workflow/rules/common.smk)."""
    from snakemake.utils import update_config

    config = yaml.safe_load((REPO / "config/config.yaml").read_text())
    for path in extra:
        update_config(config, yaml.safe_load(path.read_text()))
    settings_from_config(config)
    return config_with_defaults(config)


@pytest.mark.parametrize("extra", [(), (REPO / "config/presets/7scenes-kitchen.yaml",)], ids=["default", "7scenes"])
def test_each_stage_gets_the_settings_of_its_sections(extra):
    """A job built from its stage's sections (what its rule passes) has the settings the
    whole config gives for every section the stage reads; the sections are copies (the
    config is not changed) and the index's frame sets do not depend on the batch size."""
    from depthgt import registry
    from depthgt.settings import STAGES, TOP_LEVEL_KEYS, stage_config, stage_settings

    config = _validated(*extra)
    before = json.dumps(config, sort_keys=True)
    whole = settings_from_config(config)
    for stage, spec in STAGES.items():
        assert set(spec.top) <= set(TOP_LEVEL_KEYS) and "sources" not in spec.top, stage
        names = {"model": "lapden"} if stage == "train" else {}
        part = stage_config(config, stage, **names)
        assert list(part) == list(spec.top), stage
        own = stage_settings(part, stage, **names)
        assert stage_settings(config, stage, **names) == own  # the whole config narrowed to the same
        for top in spec.top:
            if top == "enhance":
                assert own.enhance.rde == whole.enhance.rde or stage != "rde"
            elif not (stage == "index" and top == "frameset"):
                fields = [p.split(".", 1)[1] for p in spec.sections if p.startswith(f"{top}.")]
                if fields:  # the stage reads only these keys of the section (e.g. evaluation.split)
                    for field in fields:
                        assert getattr(getattr(own, top), field) == getattr(getattr(whole, top), field), (stage, field)
                else:
                    assert getattr(own, top) == getattr(whole, top), (stage, top)
    assert "batch_size" not in stage_config(config, "index")["frameset"]
    assert stage_settings(config, "index").frameset.targets(100) == whole.frameset.targets(100)
    for model, method in registry.learned().items():
        part = stage_config(config, "train", model=method.settings_key)
        assert list(part["enhance"]["models"]) == [method.settings_key]
        assert stage_settings(part, "train", model=method.settings_key).train(model) == whole.train(model)
    # the GT's sections (the dataset card) are the frame sets' and the split
    assert set(STAGES["dataset"].top) == {*STAGES["frameset"].top, "split"}
    assert json.dumps(config, sort_keys=True) == before


def test_the_rules_pass_the_stage_table_and_the_scripts_pass_only_that():
    """One table of sections (settings.STAGES): every stage is what a rule passes as its
    `config` param, and no workflow script hands its job the whole snakemake.config."""
    from depthgt.settings import STAGES

    rules = "\n".join(p.read_text() for p in sorted((REPO / "workflow/rules").glob("*.smk")))
    for stage in STAGES:
        assert f'stage_config(config, "{stage}"' in rules, stage
    for script in sorted((REPO / "workflow/scripts").glob("*.py")):
        assert "snakemake.config" not in script.read_text(), script.name


def test_unknown_stage_and_bad_config_are_named():
    from depthgt.settings import stage_config

    with pytest.raises(KeyError, match="unknown stage 'fuse'"):
        stage_config({}, "fuse")
    with pytest.raises(ConfigError, match="must be a mapping"):
        stage_config([], "index")
    with pytest.raises(ConfigError, match=r"frameset.stride: must be >= 1"):
        settings_from_config(stage_config({"frameset": {"stride": 0}}, "frameset"))


def test_a_check_between_sections_runs_where_the_stage_reads_both():
    """patches.size <= resize: checked for the whole config and for the stages that read
    both (frame sets), not for the RDE job, which reads resize and not patches (the
    default patch size of 128 would not fit its resize of 64)."""
    from depthgt.settings import stage_settings

    small = {"resize": 64, "patches": {"size": 32}, "enhance": {"rde": {"voxel_m": 0.04}}}
    assert stage_settings(small, "rde").resize == 64 and stage_settings(small, "rde").enhance.rde.voxel_m == 0.04
    assert stage_settings(small, "frameset").patches.size == 32
    for bad in (
        lambda: settings_from_config({"resize": 64}),
        lambda: stage_settings({"resize": 64}, "frameset"),
        lambda: stage_settings({"resize": 64}, "dataset"),
    ):
        with pytest.raises(ConfigError, match=r"patches.size: 128 does not fit in the 64x64 working resolution"):
            bad()


def test_the_embedded_defaults_apply_wherever_snakemake_starts(tmp_path):
    """`-s path/Snakefile -d elsewhere --configfile mine.yaml` plans what the same config
    plans in the checkout: mine.yaml over config/config.yaml (target_step 2 there, 1 in
    the settings), not over the settings' defaults alone; a working directory with its own
    config/config.yaml (`depthgt build -d DIR`) keeps it as the whole config."""
    from conftest import make_workdir, snakemake

    mine = {"sources": [{"name": "syn", "kind": "synthetic", "scenes": ["room_000"], "options": {"n_frames": 40}}]}
    (tmp_path / "mine.yaml").write_text(yaml.safe_dump(mine))
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    expected = FrameSetSettings(**_validated(tmp_path / "mine.yaml")["frameset"]).batches(40)
    assert expected == [(6, 32)]  # target_step 2 of config/config.yaml

    def planned(wd, *args):
        text = snakemake(wd, "-n", "framesets", *args).stdout
        return sorted({line.split("/")[-1] for line in text.split() if line.endswith(".zip")})

    assert planned(elsewhere, "--configfile", str(tmp_path / "mine.yaml")) == [
        f"{a:06d}-{b:06d}.zip" for a, b in expected
    ]
    own = make_workdir(tmp_path / "own", mine)
    assert planned(own) == ["000006-000033.zip"]  # its own config, the settings' defaults (target_step 1)


def test_the_rules_and_the_stages_ask_the_registries_not_names():
    """Rules, workflow scripts, the GT stage, the jobs and the settings never compare a
    registration method's or a source kind's name: they ask the entry's properties
    (``uses_source_poses``, ``pretrained_encoder``, ``cost``; ``has_truth``), so that a
    new method or kind is its module and one entry."""
    from depthgt.registration.methods import METHODS
    from depthgt.sources.base import KINDS

    names = "|".join(sorted(map(re.escape, {*METHODS, *KINDS})))
    compared = re.compile(
        rf"""[=!]=\s*["'](?:{names})["']|["'](?:{names})["']\s*[=!]=|\bin\s*[(\[{{]\s*["'](?:{names})["']"""
    )
    files = [*_rule_files(REPO), *sorted((REPO / "workflow/scripts").glob("*.py"))]
    files += [p for d in ("gt", "jobs", "registration") for p in sorted((REPO / "src/depthgt" / d).rglob("*.py"))]
    files += sorted((REPO / "src/depthgt").rglob("settings*.py"))
    found = [f"{p.relative_to(REPO)}: {m.group(0)}" for p in files for m in compared.finditer(p.read_text())]
    assert not found, "names compared where a registry entry's property belongs:\n" + "\n".join(found)
    assert compared.search('if SETTINGS.registration.method == "overfit":') and compared.search('kind != "synthetic"')
