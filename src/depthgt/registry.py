"""The one registry of evaluation methods and trainable models (torch-free).

Every name a user can put in ``evaluation.methods`` is an entry here, with the label
the tables print and its kind:

* ``input``: the raw depth as it is (the reference row of the tables);
* ``filter``: a classical filter, run by the baseline function of the same name in
  :data:`depthgt.enhance.baselines.BASELINES`;
* ``learned``: a network trained by the workflow (rule ``train_model``) on the patch
  pairs of ``trains_on`` (``depthgt``: depthgt's GT, ``results/dataset``; ``rde``: the
  global-reconstruction GT, ``results/rde``), built by ``builder`` (a key of
  :data:`MODELS`) with ``model_params`` unless the config's
  ``enhance.models[settings_key]`` says otherwise, and run by the ``learned`` baseline.

Every trainable architecture is one :class:`Model` entry of :data:`MODELS`: its builder,
its loss and the loss terms its log records, the functions named by dotted path and
imported only when a model is built (this module stays torch-free).

The settings (:mod:`depthgt.settings`), the workflow rules (``workflow/rules/enhance.smk``),
the tables (:mod:`depthgt.eval.tables`), the training (:mod:`depthgt.enhance.train`) and
the baselines all read these tables; ``tests/test_registry.py`` checks that they agree.
Adding a filter baseline = one entry here + its function in ``enhance/baselines.py``;
adding a learned model = its module (builder and loss) + one :class:`Model` entry + one
``learned`` :class:`Method` entry (docs/development.md).
"""

from __future__ import annotations

from dataclasses import dataclass, field

__all__ = [
    "Model",
    "MODELS",
    "Method",
    "METHODS",
    "KINDS",
    "TRAINS_ON",
    "learned",
    "builders",
    "label",
    "log_columns",
    "training_priority",
]

KINDS = ("input", "filter", "learned")
TRAINS_ON = ("depthgt", "rde")


@dataclass(frozen=True)
class Model:
    """One trainable architecture.

    Attributes:
        name: its name (a learned method's ``builder``, ``TrainSettings.model``).
        build: ``"module:function"``: keyword parameters (``model_params``) -> ``nn.Module``
            mapping depth (B, 1, H, W) metres to a list of depth maps, finest last.
        loss: ``"module:function"``: ``loss(outputs, batch, **loss_params) -> (total,
            terms)``, ``terms`` a dict of floats: ``total`` and exactly ``log_terms``.
        log_terms: the loss terms the loss log records besides ``total`` (its columns,
            :func:`log_columns`); a loss that reports another term, or not one of these,
            stops the training with an error (:mod:`depthgt.enhance.train`).
        pair_cpu_ms: CPU milliseconds that one epoch costs per training patch pair on one
            thread (its steps, and its share of the validation), with the default config's
            ``model_params``. The workflow's estimate of a training's length, so that the
            longest trainings start first (rule ``train_model``'s priority,
            :func:`training_priority`); it schedules, it decides no result.
    """

    name: str
    build: str
    loss: str
    log_terms: tuple[str, ...]
    pair_cpu_ms: float

    def __post_init__(self):
        for what in ("build", "loss"):
            if getattr(self, what).count(":") != 1:
                raise ValueError(
                    f"registry model {self.name!r}: {what} must be 'module:function', got {getattr(self, what)!r}"
                )
        if not self.pair_cpu_ms > 0:
            raise ValueError(f"registry model {self.name!r}: pair_cpu_ms must be > 0, got {self.pair_cpu_ms}")
        if "total" in self.log_terms or len(set(self.log_terms)) != len(self.log_terms):
            raise ValueError(
                f"registry model {self.name!r}: log_terms must be distinct and without 'total', got {self.log_terms}"
            )


# pair_cpu_ms: the default build of bfd25c9 on a 2-core AVX-512 machine (one thread per
# training, two side by side), its benchmarks/train/*.tsv seconds over epochs x 490 training
# pairs (62 steps of 8, and 180 validation pairs): LapDEN 557 s and RDE 518 s over 30 epochs
# (their mean), SDD 899 s and DDRNet 520 s over 45.
MODELS: dict[str, Model] = {
    m.name: m
    for m in (
        Model(
            "lapden",
            build="depthgt.enhance.lapden:build_lapden",
            loss="depthgt.enhance.losses:lapden_loss_from_params",
            log_terms=("depth", "grad", "normal", "structure"),
            pair_cpu_ms=36.6,
        ),
        Model(
            "ddrnet",
            build="depthgt.enhance.learned:DDRNetDenoise",
            loss="depthgt.enhance.learned:ddrnet_loss",
            log_terms=("depth", "normal"),
            pair_cpu_ms=23.6,
        ),
        Model(
            "sdd",
            build="depthgt.enhance.learned:SDDUNet",
            loss="depthgt.enhance.learned:sdd_loss",
            log_terms=("depth", "smooth"),
            pair_cpu_ms=40.8,
        ),
    )
}


def training_priority(builder: str, epochs: int) -> int:
    """The scheduling priority of a training (rule ``train_model``): its estimated CPU
    milliseconds per training pair, ``epochs`` x the builder's ``pair_cpu_ms``. Where fewer
    cores than trainings run them, the longest starts first: the four default trainings on
    2 cores end with the longest one's lane, not behind the evaluations.

    >>> training_priority("sdd", 45) > training_priority("lapden", 30) > training_priority("ddrnet", 45)
    True
    """
    if builder not in MODELS:
        raise KeyError(f"unknown model {builder!r}; known: {', '.join(MODELS)}")
    return max(1, round(epochs * MODELS[builder].pair_cpu_ms))


def log_columns(model: str) -> tuple[str, ...]:
    """The columns of a model's ``loss_log.csv``: epoch, split, total, its loss terms,
    batches, seconds.

    >>> log_columns("sdd")
    ('epoch', 'split', 'total', 'depth', 'smooth', 'batches', 'seconds')
    """
    if model not in MODELS:
        raise KeyError(f"unknown model {model!r}; known: {', '.join(MODELS)}")
    return ("epoch", "split", "total", *MODELS[model].log_terms, "batches", "seconds")


@dataclass(frozen=True)
class Method:
    """One evaluation method.

    Attributes:
        name: the name in the config, file names and tables' long form.
        label: the row label of the tables.
        kind: ``input``, ``filter`` or ``learned``.
        baseline: the :data:`~depthgt.enhance.baselines.BASELINES` entry that runs it.
        trains_on: learned only: ``depthgt`` or ``rde``.
        builder: learned only: the trainable model (a key of :data:`MODELS`).
        settings_key: learned only: the ``enhance.models`` entry with its training
            settings (RDE trains LapDEN with LapDEN's entry).
        model_params: learned only: builder parameters when the config gives none.
    """

    name: str
    label: str
    kind: str
    baseline: str
    trains_on: str | None = None
    builder: str | None = None
    settings_key: str | None = None
    model_params: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"registry method {self.name!r}: kind must be one of {KINDS}, got {self.kind!r}")
        learned = self.kind == "learned"
        if learned != (self.trains_on is not None) or learned != (self.builder is not None):
            raise ValueError(
                f"registry method {self.name!r}: trains_on and builder are set exactly for learned methods"
            )
        if learned and self.builder not in MODELS:
            raise ValueError(
                f"registry method {self.name!r}: builder must be one of {list(MODELS)}, got {self.builder!r}"
            )
        if learned and self.trains_on not in TRAINS_ON:
            raise ValueError(
                f"registry method {self.name!r}: trains_on must be one of {TRAINS_ON}, got {self.trains_on!r}"
            )
        if learned and self.settings_key is None:
            object.__setattr__(self, "settings_key", self.name)


# The order here is the order of the tables' rows and of the default evaluation.methods.
METHODS: dict[str, Method] = {
    m.name: m
    for m in (
        Method("input", "Input (raw depth)", "input", baseline="input"),
        Method("rgf", "RGF", "filter", baseline="rgf"),
        Method("jf", "JF", "filter", baseline="jf"),
        Method(
            "ddrnet", "DDRNet (denoising net)", "learned", baseline="learned", trains_on="depthgt", builder="ddrnet"
        ),
        Method(
            "sdd", "SDD (single-view depth terms)", "learned", baseline="learned", trains_on="depthgt", builder="sdd"
        ),
        Method(
            "rde",
            "RDE (LapDEN on TSDF GT)",
            "learned",
            baseline="learned",
            trains_on="rde",
            builder="lapden",
            settings_key="lapden",
            model_params={"preset": "default"},
        ),
        Method(
            "lapden",
            "LapDEN (depthgt GT)",
            "learned",
            baseline="learned",
            trains_on="depthgt",
            builder="lapden",
            model_params={"preset": "default"},
        ),
    )
}


def learned() -> dict[str, Method]:
    """The trainable methods (kind ``learned``), in registry order."""
    return {name: m for name, m in METHODS.items() if m.kind == "learned"}


def builders() -> set[str]:
    """Names of the model builders the learned methods use."""
    return {m.builder for m in learned().values()}


def label(name: str) -> str:
    """Table label of a method (the name itself when it is not registered)."""
    return METHODS[name].label if name in METHODS else name
