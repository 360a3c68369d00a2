"""cube_check: a measure the check could not make is NULL

obb_error, edge_error, flatness_rms and perpendicularity_deg may be NULL: a cube scan that saw
no two adjacent side faces has no perpendicularity (and a scan that found no face, no edge).
Every row stored before has all four.

Revision ID: 0013_cube_check_unmeasured
Revises: 0012_calibration_range_model
Create Date: 2026-11-28 18:00:00
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = '0013_cube_check_unmeasured'
down_revision: str | None = '0012_calibration_range_model'
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

COLUMNS = ('obb_error', 'edge_error', 'flatness_rms', 'perpendicularity_deg')


def upgrade() -> None:
    """Apply this revision (the four measures may be NULL)."""
    with op.batch_alter_table('cube_check', schema=None) as batch_op:
        for name in COLUMNS:
            batch_op.alter_column(name, existing_type=sa.Float(), nullable=True)


def downgrade() -> None:
    """Undo this revision (rows with a measure missing are dropped: the column cannot hold
    them)."""
    condition = ' OR '.join(f'{name} IS NULL' for name in COLUMNS)
    op.execute(f'DELETE FROM cube_check WHERE {condition}')
    with op.batch_alter_table('cube_check', schema=None) as batch_op:
        for name in COLUMNS:
            batch_op.alter_column(name, existing_type=sa.Float(), nullable=False)
