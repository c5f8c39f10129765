"""The evaluation's wandb table: one type per column (issue: `stage=eval` crashed with the default logger)."""
import math

import pytest

from topocut.eval.report import CSV_COLUMNS, wandb_data


def _row(**kw):
    row = {c: None for c in CSV_COLUMNS}
    row.update(kw)
    return row


def test_a_missing_value_above_a_bool_builds_a_wandb_table():
    wandb = pytest.importorskip("wandb")
    rows = [_row(policy="oracle", split="in", task="slice", R_hat_mean=1.0),  # the reference: no difference, no tie
            _row(policy="dp3", split="in", task="slice", R_hat_mean=0.4, dR_hat_tie=True, dR_hat_mean=-0.6)]
    with pytest.raises(TypeError, match="incompatible types"):  # what the report handed wandb before
        wandb.Table(columns=CSV_COLUMNS, data=[["" if r[c] is None else r[c] for c in CSV_COLUMNS] for r in rows])
    data = wandb_data(rows)
    table = wandb.Table(columns=CSV_COLUMNS, data=data)
    tie = CSV_COLUMNS.index("dR_hat_tie")
    assert math.isnan(data[0][tie]) and data[1][tie] == 1.0
    assert data[0][CSV_COLUMNS.index("policy")] == "oracle" and len(table.data) == 2
