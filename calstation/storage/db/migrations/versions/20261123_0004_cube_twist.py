"""cube check twist of the side faces

Revision ID: 0004_cube_twist
Revises: 0003_run_unit_serial
Create Date: 2026-11-23 18:00:00
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op


revision: str = '0004_cube_twist'
down_revision: str | None = '0003_run_unit_serial'
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    """Apply this revision."""
    with op.batch_alter_table('cube_check', schema=None) as batch_op:
        batch_op.add_column(sa.Column('twist_deg', sa.Float(), nullable=True))
        batch_op.add_column(sa.Column('twist_sigma_deg', sa.Float(), nullable=True))


def downgrade() -> None:
    """Undo this revision (the twist of older checks is dropped with its columns)."""
    with op.batch_alter_table('cube_check', schema=None) as batch_op:
        batch_op.drop_column('twist_sigma_deg')
        batch_op.drop_column('twist_deg')
