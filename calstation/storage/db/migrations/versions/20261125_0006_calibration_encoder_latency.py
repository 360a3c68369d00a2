"""calibration.encoder_latency_s and its sigma (the estimated lidar–encoder time offset)

Revision ID: 0006_calibration_encoder_latency
Revises: run_motor_stop_artifact_status
Create Date: 2026-11-25 14:00:00
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = '0006_calibration_encoder_latency'
down_revision: str | None = 'run_motor_stop_artifact_status'
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    """Apply this revision (existing calibrations have no estimate: NULL)."""
    with op.batch_alter_table('calibration', schema=None) as batch_op:
        batch_op.add_column(sa.Column('encoder_latency_s', sa.Float(), nullable=True))
        batch_op.add_column(sa.Column('sigma_encoder_latency_s', sa.Float(), nullable=True))


def downgrade() -> None:
    """Undo this revision (the estimates are dropped)."""
    with op.batch_alter_table('calibration', schema=None) as batch_op:
        batch_op.drop_column('sigma_encoder_latency_s')
        batch_op.drop_column('encoder_latency_s')
