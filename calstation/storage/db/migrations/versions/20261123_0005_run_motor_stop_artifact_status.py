"""run.motor_stop (how the motor was stopped) and artifact.status (complete or partial)

Revision ID: run_motor_stop_artifact_status
Revises: 0004_cube_twist
Create Date: 2026-11-23 18:30:00
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = 'run_motor_stop_artifact_status'
down_revision: str | None = '0004_cube_twist'
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    """Apply this revision."""
    with op.batch_alter_table('run', schema=None) as batch_op:
        batch_op.add_column(sa.Column('motor_stop', sa.JSON(), nullable=True))
    with op.batch_alter_table('artifact', schema=None) as batch_op:
        batch_op.add_column(sa.Column('status', sa.String(length=16), nullable=False,
                                      server_default='complete'))


def downgrade() -> None:
    """Undo this revision (the tables are rebuilt with their rows; partial recordings stay
    artifacts, without their status)."""
    with op.batch_alter_table('artifact', schema=None) as batch_op:
        batch_op.drop_column('status')
    with op.batch_alter_table('run', schema=None) as batch_op:
        batch_op.drop_column('motor_stop')
