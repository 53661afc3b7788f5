"""The dataset in users' hands: GTDataset over the built manifests, the export to plain
files, the dataset card and `depthgt verify`, on the tiny workflow config."""

from __future__ import annotations

import json
import os
import pickle
import shutil
import subprocess
import sys
import zipfile
from collections import Counter
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from conftest import TINY
from torch.utils.data import DataLoader

import depthgt
from depthgt.cli import main as cli_main
from depthgt.data import GTDataset, export_dataset, training_fields
from depthgt.data import export as export_mod
from depthgt.enhance.train import TrainOutputs, patch_dataset, train
from depthgt.errors import DepthGTError
from depthgt.gt import store
from depthgt.gt.card import code_version, verify
from depthgt.io import read_exr, read_rgb
from depthgt.settings import SPLITS, TrainSettings

PATCH = TINY["patches"]["size"]
FRAME = TINY["resize"]  # 256 in the default config


@pytest.fixture(scope="module")
def built(tiny_build) -> Path:
    return tiny_build  # conftest: built once per session, read-only here (_copy_results for damage)


@pytest.fixture()
def results(built, monkeypatch) -> Path:
    monkeypatch.chdir(built)  # the manifests' locations are relative to the working directory
    return built / "results"


def _copy_results(built: Path, dest: Path) -> Path:
    """A copy of the built dataset (shards and manifests) that a test may damage."""
    for sub in ("dataset", "framesets"):
        shutil.copytree(built / "results" / sub, dest / "results" / sub)
    return dest


def _member_data_offset(shard: Path, name: str) -> int:
    """Byte offset in the shard of the first data byte of a stored member."""
    with zipfile.ZipFile(shard) as z:
        info = z.getinfo(name)
    with shard.open("rb") as f:
        f.seek(info.header_offset + 26)
        n_name, n_extra = (int.from_bytes(f.read(2), "little") for _ in range(2))
    return info.header_offset + 30 + n_name + n_extra


def _flip_byte(path: Path, offset: int) -> None:
    data = bytearray(path.read_bytes())
    data[offset] ^= 0xFF
    path.write_bytes(bytes(data))


# --------------------------------------------------------------------------- GTDataset


@pytest.mark.parametrize("split", SPLITS)
def test_every_manifest_row_comes_out_of_a_dataloader_once(results, split):
    manifest = pd.read_parquet(results / "dataset" / f"{split}.parquet")
    assert len(manifest) > 0
    ds = GTDataset(results, split)
    seen = Counter()
    for batch in DataLoader(ds, batch_size=4, num_workers=2):
        b = len(batch["patch"])
        for key in ("input", "gt", "sigma", "truth"):
            assert batch[key].shape == (b, 1, PATCH, PATCH) and batch[key].dtype == torch.float32, key
        assert batch["rgb"].shape == (b, 3, PATCH, PATCH) and 0 <= batch["rgb"].min() and batch["rgb"].max() <= 1
        assert batch["K"].shape == (b, 3, 3)
        assert ((batch["sigma"] > 0) == (batch["gt"] > 0)).all()  # 0 = no GT, positive wherever there is
        assert set(batch["split"]) == {split}
        seen.update(zip(batch["dataset"], batch["scene"], batch["target"].tolist(), batch["patch"].tolist()))
    want = Counter(
        zip(manifest["dataset"], manifest["scene"], manifest["target"].astype(int), manifest["patch"].astype(int))
    )
    assert seen == want and set(seen.values()) == {1}


def test_patch_samples_are_the_shards_arrays(results):
    ds = GTDataset(results, "train")
    row = ds.table.iloc[3]
    npz = store.read_patches_at(row["frameset"])  # the crops, cut from the frame set's images
    K = np.asarray(store.read_json(f"{row['frameset']}/frameset.json")["K"], dtype=np.float32)
    s, j = ds[3], int(row["patch"])
    assert np.array_equal(s["input"][0].numpy(), npz["input"][j]) and np.array_equal(s["gt"][0].numpy(), npz["gt"][j])
    assert np.array_equal(s["truth"][0].numpy(), npz["truth"][j])
    assert np.array_equal(s["rgb"].numpy(), npz["rgb"][j].transpose(2, 0, 1) / np.float32(255))
    y0, x0 = npz["boxes"][j][:2]
    assert (row["y0"], row["x0"]) == (y0, x0)
    assert s["K"][0, 2].item() == pytest.approx(K[0, 2] - x0) and s["K"][1, 2].item() == pytest.approx(K[1, 2] - y0)
    assert (s["dataset"], s["scene"], s["target"], s["patch"]) == (row["dataset"], row["scene"], row["target"], j)


def test_frames_of_the_test_split(results):
    fs = pd.read_parquet(results / "dataset" / "framesets.parquet")
    want = fs[(fs["split"] == "test") & (fs["status"] == "ok")]
    ds = GTDataset(results, "test", kind="frames")
    assert len(ds) == len(want) > 0
    s = ds[0]
    for key in ("input", "gt", "sigma", "truth"):
        assert s[key].shape == (1, FRAME, FRAME), key
    assert s["rgb"].shape == (3, FRAME, FRAME) and s["patch"] == -1
    rec = store.read_frameset_at(want["frameset"].iloc[0])
    assert np.array_equal(s["gt"][0].numpy(), rec.gt_m) and np.array_equal(s["input"][0].numpy(), rec.input_m)
    assert np.array_equal(s["sigma"][0].numpy(), np.where(rec.gt_m > 0, rec.gt_sigma_m, 0))
    assert np.allclose(s["K"].numpy(), rec.meta["K"])


@pytest.mark.parametrize("context", ["fork", "spawn"])
def test_workers_open_their_own_shards(results, context):
    ds = GTDataset(results, "train", transform=training_fields)
    first = ds[0]  # this process now holds the shard open: a forked worker must not read through it
    assert ds._reader.open_shards
    loader = DataLoader(ds, batch_size=5, num_workers=2, multiprocessing_context=context)
    got = torch.cat([b["gt"] for b in loader])
    assert torch.equal(got, torch.stack([ds[i]["gt"] for i in range(len(ds))]))
    assert torch.equal(got[0], first["gt"]) and set(first) == {"input", "gt", "rgb", "K", "sigma"}


def test_shard_reader_reopens_in_a_new_process_and_pickles_without_handles(results, monkeypatch):
    loc = pd.read_parquet(results / "dataset/train.parquet")["frameset"].iloc[0]
    shard = Path(loc.rsplit("/", 1)[0])
    reader = store.ShardReader(max_open=1)
    doc = reader.read(f"{loc}/frameset.json")
    parent_handle = reader._open[shard]
    assert reader.open_shards == [shard]
    pid = os.getpid()
    monkeypatch.setattr(os, "getpid", lambda: pid + 1)  # what a forked worker sees
    assert reader.open_shards == []
    assert reader.read(f"{loc}/frameset.json") == doc
    assert reader._open[shard] is not parent_handle and parent_handle.fp is not None  # the parent's stays open
    monkeypatch.setattr(os, "getpid", lambda: pid)
    clone = pickle.loads(pickle.dumps(reader))
    assert clone.open_shards == [] and clone.max_open == 1 and clone.read(f"{loc}/frameset.json") == doc
    other = pd.read_parquet(results / "dataset/test.parquet")["frameset"].iloc[0]
    clone.read(f"{other}/frameset.json")
    assert clone.open_shards == [Path(other.rsplit("/", 1)[0])]  # max_open=1: the older one closed


def test_missing_and_corrupt_shards_are_named(built, tmp_path):
    wd = _copy_results(built, tmp_path)
    table = pd.read_parquet(wd / "results/dataset/train.parquet")
    shard = wd / table["frameset"].iloc[0].rsplit("/", 1)[0]  # <shard>/<target>
    ds = GTDataset(wd / "results", "train")
    _flip_byte(shard, _member_data_offset(shard, f"{int(table['target'].iloc[0]):06d}/patches.npz") + 200)
    with pytest.raises(DepthGTError, match=f"{shard}.*corrupt"):
        ds[0]
    shard.unlink()
    with pytest.raises(DepthGTError, match=f"{shard} does not exist"):
        GTDataset(wd / "results", "train")[0]


def test_bad_arguments_name_the_file_or_key(results, tmp_path):
    with pytest.raises(DepthGTError, match="split must be one of"):
        GTDataset(results, "training")
    with pytest.raises(DepthGTError, match="kind must be one of"):
        GTDataset(results, "train", kind="voxels")
    with pytest.raises(DepthGTError, match=r"dataset\(s\) \['nope'\]"):
        GTDataset(results, "train", datasets=["nope"])
    with pytest.raises(DepthGTError, match=f"no manifest {tmp_path}"):
        GTDataset(tmp_path, "train")
    assert len(GTDataset(results, "train", datasets=["syn"])) == len(pd.read_parquet(results / "dataset/train.parquet"))
    with pytest.raises(IndexError, match="out of range"):
        GTDataset(results, "val")[10_000]


# --------------------------------------------------------------------------- trainer


def test_the_trainer_reads_its_patches_through_gtdataset(results, tmp_path, monkeypatch):
    ds = patch_dataset(results / "dataset/train.parquet")
    assert isinstance(ds, GTDataset) and len(ds) == len(GTDataset(results, "train"))
    ref = GTDataset(results, "train")
    for i in (0, len(ds) - 1):
        a, b = ds[i], ref[i]
        assert set(a) == {"input", "gt", "rgb", "K", "sigma"} and all(torch.equal(a[k], b[k]) for k in a)
    calls = Counter()
    original = GTDataset.__getitem__

    def counted(self, i):
        calls[self.manifest] += 1
        return original(self, i)

    monkeypatch.setattr(GTDataset, "__getitem__", counted)
    st = TrainSettings(
        model="lapden",
        model_params={"preset": "default", "channels": 4, "level_convs": [2, 2, 2], "encoder_convs": [0, 0]},
        epochs=1,
        batch_size=8,
        lr=1e-3,
        seed=3,
        progress=False,
    )
    out = train("results/dataset/train.parquet", "results/dataset/val.parquet", TrainOutputs.in_dir(tmp_path / "m"), st)
    assert out["epochs_run"] == 1
    n_train, n_val = (len(pd.read_parquet(results / f"dataset/{s}.parquet")) for s in ("train", "val"))
    assert calls == {"results/dataset/train.parquet": n_train, "results/dataset/val.parquet": n_val}


# --------------------------------------------------------------------------- export


def test_export_png16_round_trip(results, tmp_path):
    dest = tmp_path / "png"
    index = export_dataset(results, dest, "png16", progress=False)
    for split in SPLITS:
        manifest = pd.read_parquet(results / f"dataset/{split}.parquet")
        assert (index["split"] == split).sum() == len(manifest)
    assert pd.read_parquet(dest / "index.parquet").equals(index)
    assert pd.read_csv(dest / "index.csv", keep_default_na=False).astype(str).equals(index.astype(str))
    assert json.loads((dest / "card.json").read_text()) == json.loads((results / "dataset/card.json").read_text())
    ds = {s: GTDataset(results, s) for s in SPLITS}
    for row in index.iloc[[0, len(index) // 2, len(index) - 1]].itertuples():
        i = next(
            i
            for i in range(len(ds[row.split]))
            if ds[row.split].ids(i)["target"] == row.target
            and ds[row.split].ids(i)["patch"] == row.patch
            and ds[row.split].ids(i)["scene"] == row.scene
        )
        s = ds[row.split][i]
        for m in ("input", "gt", "truth"):
            back, want = export_mod.read_depth(dest / getattr(row, m), m), s[m][0].numpy()
            assert np.array_equal(back > 0, want > 0), m
            assert np.abs(back - want).max() <= 0.0005 + 1e-6, m  # 1 mm steps: within half a step
        assert np.abs(export_mod.read_depth(dest / row.sigma, "sigma") - s["sigma"][0].numpy()).max() <= 0.00005 + 1e-7
        assert np.array_equal(
            read_rgb(dest / row.rgb), np.round(s["rgb"].permute(1, 2, 0).numpy() * 255).astype(np.uint8)
        )
    assert verify(dest).ok


def test_export_exr_frames_is_exact(results, tmp_path):
    dest = tmp_path / "exr"
    index = export_dataset(results, dest, "exr", splits=["test"], kind="frames", progress=False)
    ds = GTDataset(results, "test", kind="frames")
    assert len(index) == len(ds) > 0
    for i, row in enumerate(index.itertuples()):
        s = ds[i]
        for m in ("input", "gt", "sigma", "truth"):
            back = read_exr(dest / getattr(row, m))
            assert set(back) == {"Y"} and np.array_equal(back["Y"], s[m][0].numpy()), m
        assert back["Y"].shape == (FRAME, FRAME)
    report = verify(dest)
    assert report.ok and report.kind == "export"


def test_an_interrupted_export_resumes(results, tmp_path, monkeypatch):
    dest = tmp_path / "resume"
    written = []
    original = export_mod._write_sample

    def dies_after_five(dest_, sample, files, fmt):
        if len(written) == 5:
            raise KeyboardInterrupt("killed")
        original(dest_, sample, files, fmt)
        written.append(files)

    monkeypatch.setattr(export_mod, "_write_sample", dies_after_five)
    with pytest.raises(KeyboardInterrupt):
        export_dataset(results, dest, "png16", progress=False)
    assert not (dest / "index.parquet").exists() and not (dest / "SHA256SUMS").exists()
    assert not verify(dest).ok  # an unfinished export does not verify
    monkeypatch.setattr(export_mod, "_write_sample", original)
    # what a kill -9 leaves: a temporary file of a half-written PNG; a file deleted since
    first = dest / written[0]["gt"]
    stray = first.with_name(f".{first.name}.tmp.png")
    stray.write_bytes(b"\x89PNG half")
    deleted = dest / written[1]["rgb"]
    deleted.unlink()
    kept = dest / written[2]["input"]
    mtime = kept.stat().st_mtime_ns
    resumed = export_dataset(results, dest, "png16", progress=False)
    assert kept.stat().st_mtime_ns == mtime  # complete samples are not written again
    assert deleted.is_file() and not stray.exists()
    full = export_dataset(results, tmp_path / "full", "png16", progress=False)
    assert resumed.equals(full)
    assert (dest / "SHA256SUMS").read_text() == (tmp_path / "full" / "SHA256SUMS").read_text()
    assert verify(dest).ok
    with pytest.raises(DepthGTError, match=r"export.json: .* other settings \(\['format'"):
        export_dataset(results, dest, "exr", progress=False)


def test_export_command(built, tmp_path):
    proc = subprocess.run([sys.executable, "-m", "depthgt.cli", "-h"], capture_output=True, text=True)
    assert "export" in proc.stdout and "verify" in proc.stdout
    dest = tmp_path / "cli"
    args = [
        "export",
        str(dest),
        "-d",
        str(built),
        "--split",
        "val",
        "--split",
        "test",
        "--kind",
        "frames",
        "--workers",
        "2",
    ]
    assert cli_main(args) == 0
    index = pd.read_csv(dest / "index.csv")
    assert list(index["split"].unique()) == ["val", "test"] and (index["patch"] == -1).all()
    assert cli_main(["verify", str(dest)]) == 0


def test_export_refuses_what_it_cannot_own_and_names_it(results, tmp_path, capsys):
    foreign = tmp_path / "foreign"
    (foreign / "patches").mkdir(parents=True)
    (foreign / "patches" / "mine.png").write_bytes(b"x")
    with pytest.raises(DepthGTError, match=r"foreign holds files but no export.json \(patches\)"):
        export_dataset(results, foreign, "png16", splits=["val"], progress=False)
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "export.json").write_text("{half")
    with pytest.raises(DepthGTError, match=r"export.json: not readable as an export's settings \(JSONDecodeError"):
        export_dataset(results, broken, "png16", splits=["val"], progress=False)
    with pytest.raises(DepthGTError, match="workers must be an integer >= 0, got -1"):
        export_dataset(results, tmp_path / "w", "png16", splits=["val"], workers=-1, progress=False)
    assert not (tmp_path / "w").exists()  # checked before anything is written
    with pytest.raises(DepthGTError, match=r"holds no built dataset .*nothing/results/dataset is missing"):
        export_dataset(tmp_path / "nothing" / "results", tmp_path / "n", "png16", progress=False)
    hidden = tmp_path / "hidden"  # a new disk's or Finder's hidden files are no foreign export
    hidden.mkdir()
    (hidden / ".DS_Store").write_bytes(b"x")
    export_dataset(results, hidden, "png16", splits=["val"], progress=False)
    assert verify(hidden).ok
    once = export_dataset(results, tmp_path / "once", "png16", splits=["val"], progress=False)
    twice = export_dataset(results, tmp_path / "twice", "png16", splits=["val", "val"], progress=False)
    assert twice.equals(once) and verify(tmp_path / "twice").ok
    # a destination that is a file: the command names it, no traceback
    (tmp_path / "afile").write_text("")
    assert cli_main(["export", str(tmp_path / "afile" / "x"), "-d", str(results.parent)]) == 2
    assert "afile" in capsys.readouterr().err


def test_verify_reports_a_damaged_export_instead_of_crashing(results, tmp_path):
    dest = tmp_path / "e"
    export_dataset(results, dest, "png16", splits=["val"], progress=False)
    assert verify(dest).ok
    stray = dest / "patches" / "stray.png"
    stray.write_bytes(b"x")
    report = verify(dest)
    assert len(report.problems) == 1 and "1 files not in SHA256SUMS" in report.problems[0]
    assert "stray.png" in report.problems[0]
    stray.unlink()
    (dest / "index.parquet").write_bytes(b"garbage")
    (problem,) = verify(dest).problems
    assert "index.parquet: not a readable parquet table" in problem
    (dest / "export.json").write_text("[1, 2]")  # also breaks its checksum
    assert any("export.json: not a JSON object (a list)" in p for p in verify(dest).problems)
    (dest / "SHA256SUMS").write_bytes(b"\xff\xfe not text")
    (problem,) = verify(dest).problems
    assert "SHA256SUMS: not a text checksum list" in problem
    wd = _copy_results(results.parent, tmp_path / "wd")
    (wd / "results/dataset/card.json").write_text(
        json.dumps({"format_version": store.FORMAT_VERSION, "files": {"a": {}}})
    )
    (problem,) = verify(wd).problems
    assert "card.json: not a dataset card (KeyError" in problem


# --------------------------------------------------------------------------- card and verify


def test_card_describes_the_build(results):
    card = json.loads((results / "dataset/card.json").read_text())
    fs = pd.read_parquet(results / "dataset/framesets.parquet")
    for split in SPLITS:
        assert card["splits"][split]["pairs"] == len(pd.read_parquet(results / f"dataset/{split}.parquet"))
        assert card["splits"][split]["framesets"] == ((fs["split"] == split) & (fs["status"] == "ok")).sum()
    assert {s["name"]: sorted(s["scenes"]) for s in card["sources"]} == {
        src["name"]: src["scenes"] for src in TINY["sources"]
    }
    shards = sorted(p.relative_to(results).as_posix() for p in (results / "framesets").rglob("*.zip"))
    assert shards and set(shards) <= set(card["files"])
    assert card["framesets"]["kept"] == (fs["status"] == "ok").sum() and card["framesets"]["skipped"] == 0
    assert card["settings"]["resize"] == TINY["resize"] and card["settings"]["patches"]["size"] == PATCH
    q = card["quality"]
    assert 0.9 < q["gt_completeness"] <= 1 and 0 < q["gt_median_sigma_m"] < 0.1
    assert {"truth"} <= {r["reference"] for r in q["by_dataset"]}
    assert card["depthgt"]["version"] == depthgt.__version__
    assert "# Dataset card" in (results / "dataset/card.md").read_text()


def test_code_version_outside_git(tmp_path, monkeypatch):
    assert code_version(tmp_path) == {"version": depthgt.__version__, "commit": None, "dirty": None}
    monkeypatch.setenv("PATH", str(tmp_path))  # no git at all
    assert code_version()["commit"] is None


def test_verify_names_the_changed_shard(built, tmp_path, capsys):
    wd = _copy_results(built, tmp_path)
    assert verify(wd).ok and verify(wd / "results").ok
    assert cli_main(["verify", "-d", str(wd)]) == 0
    shard = sorted((wd / "results/framesets").rglob("*.zip"))[-1]
    _flip_byte(shard, shard.stat().st_size // 2)
    report = verify(wd)
    assert not report.ok and len(report.problems) == 1 and str(shard) in report.problems[0]
    capsys.readouterr()
    assert cli_main(["verify", str(wd)]) == 1
    assert f"FAILED {shard}: sha256 differs" in capsys.readouterr().out
    # newer than the card: a scene rebuilt and the dataset not assembled again reads as such
    assert "run `depthgt build dataset` to assemble the dataset and its card again" in report.problems[0]
    card = wd / "results/dataset/card.json"
    os.utime(shard, ns=(card.stat().st_mtime_ns - 10**9,) * 2)
    assert verify(wd).problems[0].endswith("sha256 differs from the card " + f"{card} (changed or corrupt)")
    with pytest.raises(DepthGTError, match="holds no dataset card"):
        verify(tmp_path / "nothing")
    env = dict(os.environ)
    proc = subprocess.run(
        [sys.executable, "-m", "depthgt.cli", "verify", str(wd)], capture_output=True, text=True, env=env
    )
    assert proc.returncode == 1 and shard.name in proc.stdout
