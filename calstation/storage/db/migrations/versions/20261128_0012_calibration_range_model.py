"""calibration: the lidar's range model estimated with H (DESIGN §9)

range_offset (m), range_scale, incidence_bias (m at 60°) and their sigma; NULL where the range
model was not estimated (every calibration stored before).

Revision ID: 0012_calibration_range_model
Revises: 0011_database_identity
Create Date: 2026-11-28 12:00:00
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = '0012_calibration_range_model'
down_revision: str | None = '0011_database_identity'
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

COLUMNS = ('range_offset', 'sigma_range_offset', 'range_scale', 'sigma_range_scale',
           'incidence_bias', 'sigma_incidence_bias')


def upgrade() -> None:
    """Apply this revision (existing calibrations estimated no range model: NULL)."""
    with op.batch_alter_table('calibration', schema=None) as batch_op:
        for name in COLUMNS:
            batch_op.add_column(sa.Column(name, sa.Float(), nullable=True))


def downgrade() -> None:
    """Undo this revision (the range models are dropped)."""
    with op.batch_alter_table('calibration', schema=None) as batch_op:
        for name in reversed(COLUMNS):
            batch_op.drop_column(name)
