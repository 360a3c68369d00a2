"""run unit serial

The serial number of the unit a run calibrated (from the lidar driver's info, or given by the
operator), so history and trend can filter on it.

Upgrade fills it for existing runs from what their steps recorded (``unit_serial`` in a step
result, else the preflight's ``lidar.serial``). Downgrade keeps every serial in the run's first
step result (``unit_serial``) before dropping the column, so upgrading again restores it; a run
with a serial but no step at all has nowhere to keep it, and the downgrade refuses.

Revision ID: 0003_run_unit_serial
Revises: 0002
Create Date: 2026-11-23 18:30:00
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op


revision: str = '0003_run_unit_serial'
down_revision: str | None = '0002'
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

_run = sa.table('run', sa.column('id', sa.Integer), sa.column('unit_serial', sa.String(100)))
_step = sa.table(
    'step', sa.column('id', sa.Integer), sa.column('run_id', sa.Integer),
    sa.column('name', sa.String(50)), sa.column('result', sa.JSON),
)


def _serial_in(result: object) -> str | None:
    if not isinstance(result, dict):
        return None
    value = result.get('unit_serial')
    if isinstance(value, str) and value:
        return value
    lidar = result.get('lidar')
    if isinstance(lidar, dict) and isinstance(lidar.get('serial'), str) and lidar['serial']:
        return str(lidar['serial'])
    return None


def upgrade() -> None:
    """Apply this revision."""
    with op.batch_alter_table('run', schema=None) as batch_op:
        batch_op.add_column(sa.Column('unit_serial', sa.String(length=100), nullable=True))
        batch_op.create_index(batch_op.f('ix_run_unit_serial'), ['unit_serial'], unique=False)
    conn = op.get_bind()
    found: dict[int, str] = {}
    rows = conn.execute(sa.select(_step.c.run_id, _step.c.result).order_by(_step.c.id)).all()
    for run_id, result in rows:
        serial = _serial_in(result)
        if serial is not None and run_id not in found:
            found[run_id] = serial
    for run_id, serial in found.items():
        conn.execute(_run.update().where(_run.c.id == run_id).values(unit_serial=serial))


def downgrade() -> None:
    """Undo this revision, keeping each serial in the run's first step result."""
    conn = op.get_bind()
    runs = conn.execute(
        sa.select(_run.c.id, _run.c.unit_serial).where(_run.c.unit_serial.is_not(None))
    ).all()
    for run_id, serial in runs:
        steps = conn.execute(
            sa.select(_step.c.id, _step.c.result).where(_step.c.run_id == run_id)
            .order_by(_step.c.id)
        ).all()
        first = next((v for v in (_serial_in(r) for _, r in steps) if v is not None), None)
        if first == serial:  # upgrade finds it again as it is
            continue
        if not steps:
            raise RuntimeError(
                f"run {run_id} has unit serial {serial!r} but no step to keep it in; "
                "downgrading would lose it"
            )
        step_id, result = steps[0]
        kept = dict(result) if isinstance(result, dict) else {}
        kept['unit_serial'] = serial
        conn.execute(_step.update().where(_step.c.id == step_id).values(result=kept))
    # Not a batch operation: on SQLite a batch re-creates the run table, and dropping the old one
    # with foreign keys on would cascade to every step, calibration and artifact of every run.
    # SQLite 3.35+ drops a column in place.
    op.drop_index('ix_run_unit_serial', table_name='run')
    op.drop_column('run', 'unit_serial')
