"""The later CoWorld paper's published numbers, as data: ``coworld report`` puts each beside ours.

The paper: Q. Wang, J. Yang, Y. Wang, X. Jin, W. Zeng, X. Yang, "Making Offline RL Online: Collaborative World
Models for Offline Visual Reinforcement Learning", NeurIPS 2024 (arXiv 2305.15260 v4; OpenReview ucxQrked0d).
Every number is the final return's mean ± standard deviation as printed, "10 episodes over 3 seeds", each with the
table it is printed in (:attr:`Published.where`). Nothing here is derived or read off a figure: where the paper
gives only learning curves (its Figure 4, Meta-World -> RoboDesk), the cells it does not print are absent.

How the paper's columns map to this project's algorithms (its Appendix E says what each column is):

* "Offline DV2" is V-D4RL's offline DreamerV2 with the reward penalty of the dynamics ensemble's mean
  disagreement: ``dreamerv2-penalty``. This project's plain ``dreamerv2`` (the seed paper's baseline) has no column.
* "DrQ+BC": ``drq-bc``. "CURL": ``curl``. "DV2 Finetune" (Table 9: "Finetune"): ``dreamerv2-finetune``.
  "CoWorld": ``coworld`` (Meta-World -> RoboDesk: the best-source CoWorld, the source named by the pair).
* "LOMPO": ``lompo``.
* No algorithm of ours (None): "CQL" (V-D4RL's DrQ-v2 with CQL's regulariser, not our CURL+CQL), "LOMPO
  Finetune", and the multi-source CoWorld.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType


@dataclass(frozen=True)
class Published:
    """One printed cell: mean ± std of the final return, and the table that prints it."""

    mean: float
    std: float
    where: str
    """The paper's table, e.g. 'Table 3'."""


@dataclass(frozen=True)
class PaperTable:
    """The numbers of one of the paper's result tables and what they were measured on."""

    name: str
    """The ``coworld sweep --table`` grid that runs it."""
    title: str
    quality: str
    """The target datasets' quality: a number is beside ours only for a run on a dataset of this quality."""
    pairs: tuple[tuple[str, str], ...]
    """(source, target), in the paper's column order."""
    columns: tuple[tuple[str, str | None], ...]
    """(the paper's row name, our algorithm or None), in the paper's order."""
    cells: Mapping[tuple[str, str], Published]
    """(target, the paper's row name) -> the printed number."""
    averages: Mapping[str, float]
    """The paper's row name -> its printed average over the pairs ('Avg.'); absent where none is printed."""

    def algorithm(self, column: str) -> str | None:
        return dict(self.columns)[column]

    def algos(self) -> tuple[str, ...]:
        """Our algorithms that have a column, in the paper's order."""
        return tuple(algo for _, algo in self.columns if algo is not None)

    def number(self, algo: str, source: str | None, target: str) -> Published | None:
        """The paper's number for ``algo`` on ``target``, or None; a run with a source needs the paper's source."""
        pair = dict((t, s) for s, t in self.pairs)
        if target not in pair or (source is not None and source != pair[target]):
            return None
        for column, ours in self.columns:
            if ours == algo:
                return self.cells.get((target, column))
        return None


def _cells(
    targets: tuple[str, ...], where: str, rows: Mapping[str, tuple[tuple[float, float], ...]]
) -> dict[tuple[str, str], Published]:
    """A printed table, row by row in the targets' order, as cells."""
    cells = {}
    for column, values in rows.items():
        if len(values) != len(targets):
            raise ValueError(f"{where} {column}: {len(values)} cells for {len(targets)} pairs")
        for target, (mean, std) in zip(targets, values, strict=True):
            cells[(target, column)] = Published(mean, std, where)
    return cells


DMC_PAIRS = (
    ("walker_walk", "walker_downhill"),
    ("walker_walk", "walker_uphill"),
    ("walker_walk", "walker_nofoot"),
    ("cheetah_run", "cheetah_downhill"),
    ("cheetah_run", "cheetah_uphill"),
    ("cheetah_run", "cheetah_nopaw"),
)
"""The later paper's six DMC pairs (WW -> WD, WU, WN; CR -> CD, CU, CN), its Tables 3 and 9."""
_DMC_TARGETS = tuple(target for _, target in DMC_PAIRS)

DMC_MEDIUM_REPLAY = PaperTable(
    name="dmc-mr",
    title="DMC, medium-replay datasets (Table 3)",
    quality="medium-replay",
    pairs=DMC_PAIRS,
    columns=(
        ("Offline DV2", "dreamerv2-penalty"),
        ("DrQ+BC", "drq-bc"),
        ("CQL", None),
        ("CURL", "curl"),
        ("LOMPO", "lompo"),
        ("DV2 Finetune", "dreamerv2-finetune"),
        ("LOMPO Finetune", None),
        ("CoWorld", "coworld"),
    ),
    cells=MappingProxyType(
        _cells(
            _DMC_TARGETS,
            "Table 3",
            {
                "Offline DV2": ((435, 22), (139, 4), (214, 4), (243, 7), (3, 1), (51, 4)),
                "DrQ+BC": ((291, 10), (299, 15), (318, 40), (663, 15), (202, 12), (132, 33)),
                "CQL": ((46, 19), (64, 32), (29, 2), (2, 1), (52, 57), (111, 157)),
                "CURL": ((43, 5), (21, 3), (23, 3), (26, 7), (4, 2), (11, 4)),
                "LOMPO": ((462, 87), (260, 21), (460, 9), (395, 52), (46, 19), (120, 4)),
                "DV2 Finetune": ((379, 23), (354, 29), (407, 37), (702, 41), (208, 22), (454, 82)),
                "LOMPO Finetune": ((209, 21), (141, 27), (212, 9), (142, 29), (17, 11), (105, 12)),
                "CoWorld": ((629, 9), (407, 141), (426, 32), (745, 28), (225, 20), (493, 10)),
            },
        )
    ),
    averages=MappingProxyType(
        {
            "Offline DV2": 181,
            "DrQ+BC": 355,
            "CQL": 51,
            "CURL": 21,
            "LOMPO": 291,
            "DV2 Finetune": 417,
            "LOMPO Finetune": 137,
            "CoWorld": 488,
        }
    ),
)
"""Table 3, "Mean rewards and standard deviations of 10 episodes in offline DMC over 3 seeds" (medium-replay:
its Section 4.1, "all the samples in the replay buffer ... until the policy attains medium-level performance")."""

DMC_MEDIUM_EXPERT = PaperTable(
    name="dmc-me",
    title="DMC, medium-expert datasets (Table 9)",
    quality="medium-expert",
    pairs=DMC_PAIRS,
    columns=(
        ("Offline DV2", "dreamerv2-penalty"),
        ("DrQ+BC", "drq-bc"),
        ("LOMPO", "lompo"),
        ("Finetune", "dreamerv2-finetune"),
        ("CoWorld", "coworld"),
    ),
    cells=MappingProxyType(
        _cells(
            _DMC_TARGETS,
            "Table 9",
            {
                "Offline DV2": ((450, 24), (141, 1), (214, 8), (248, 9), (3, 0), (48, 3)),
                "DrQ+BC": ((808, 47), (762, 61), (808, 45), (862, 13), (454, 12), (730, 17)),
                "LOMPO": ((548, 245), (449, 117), (688, 97), (174, 29), (19, 10), (113, 35)),
                "Finetune": ((784, 46), (671, 65), (851, 91), (858, 9), (428, 49), (833, 7)),
                "CoWorld": ((848, 9), (774, 29), (919, 7), (871, 13), (475, 16), (844, 1)),
            },
        )
    ),
    averages=MappingProxyType({"Offline DV2": 184, "DrQ+BC": 737, "LOMPO": 332, "Finetune": 738, "CoWorld": 789}),
)
"""Table 9, "Performance on DMC medium-expert dataset ... 10 episodes over 3 seeds" (Appendix B.2: "all the samples
in the replay buffer during the training process until the policy attains expert-level performance")."""

ROBODESK_PAIRS = (
    ("mw_button_press", "robodesk_push_button"),
    ("mw_window_close", "robodesk_open_slide"),
    ("mw_drawer_close", "robodesk_drawer_open"),
    ("mw_handle_press", "robodesk_upright_block_off_table"),
)
"""Meta-World -> RoboDesk, the later paper's Figure 4 (Button Press -> Push Button, Window Close -> Open Slide,
Drawer Close -> Drawer Open, Handle Press -> Upright Block off Table; the same sources its multi-source CoWorld
chose, Table 13)."""

META_WORLD_TO_ROBODESK = PaperTable(
    name="robodesk",
    title="Meta-World -> RoboDesk (Figure 4; numbers from Tables 4 and 6)",
    quality="medium-replay",
    pairs=ROBODESK_PAIRS,
    columns=(
        ("CoWorld (Best-Source)", "coworld"),
        ("CoWorld (Multi-Source)", None),
        ("Offline DV2", "dreamerv2-penalty"),
        ("DV2 Finetune", "dreamerv2-finetune"),
    ),
    cells=MappingProxyType(
        {
            # Table 6 compares "the original CoWorld" with a jointly trained world model on two of the pairs
            ("robodesk_push_button", "CoWorld (Best-Source)"): Published(428, 42, "Table 6"),
            ("robodesk_open_slide", "CoWorld (Best-Source)"): Published(202, 19, "Table 6"),
            # Table 4 gives CoWorld low-dimensional sources; Offline DV2 has no source, so its row is the plain one
            ("robodesk_push_button", "Offline DV2"): Published(347, 24, "Table 4"),
            ("robodesk_open_slide", "Offline DV2"): Published(156, 46, "Table 4"),
        }
    ),
    averages=MappingProxyType({}),
)
"""Figure 4 prints learning curves only. Its final numbers appear in text for two pairs: CoWorld in Table 6 and
Offline DV2 in Table 4. DV2 Finetune's only number there (Table 5) is for sparse source rewards, so it is left out,
as are Drawer Open and Upright Block off Table."""

TABLES: Mapping[str, PaperTable] = MappingProxyType(
    {table.name: table for table in (DMC_MEDIUM_REPLAY, DMC_MEDIUM_EXPERT, META_WORLD_TO_ROBODESK)}
)
"""The paper's tables by the name of the sweep grid that runs each."""


def published(algo: str, source: str | None, target: str, quality: str | None) -> Published | None:
    """The paper's number for a run of ``algo`` on ``source -> target`` with a ``quality`` dataset, or None.

    The tables' targets do not repeat within a quality, so at most one number matches.
    """
    for table in TABLES.values():
        if table.quality == quality:
            number = table.number(algo, source, target)
            if number is not None:
                return number
    return None
