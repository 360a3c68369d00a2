"""cube_check.flatness_excess and range_noise: the worst face's RMS beyond what the range noise
explains (what the flatness limit judges) and that noise, measured on the faces

Revision ID: 0009_cube_flatness_excess
Revises: 0008_campaigns_locations
Create Date: 2026-11-26 22:10:00
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = '0009_cube_flatness_excess'
down_revision: str | None = '0008_campaigns_locations'
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    """Apply this revision (checks stored before it judged the raw RMS: NULL)."""
    with op.batch_alter_table('cube_check', schema=None) as batch_op:
        batch_op.add_column(sa.Column('flatness_excess', sa.Float(), nullable=True))
        batch_op.add_column(sa.Column('range_noise', sa.Float(), nullable=True))


def downgrade() -> None:
    """Undo this revision (the raw RMS stays in flatness_rms)."""
    with op.batch_alter_table('cube_check', schema=None) as batch_op:
        batch_op.drop_column('range_noise')
        batch_op.drop_column('flatness_excess')
