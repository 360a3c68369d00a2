"""calibration.predicted_error_m: the reconstruction error the calibration predicts over the
recipe's work volume (the accuracy budget)

Revision ID: 0007_calibration_predicted_error
Revises: 0006_calibration_encoder_latency
Create Date: 2026-11-26 20:30:00
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = '0007_calibration_predicted_error'
down_revision: str | None = '0006_calibration_encoder_latency'
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    """Apply this revision (calibrations stored before it have no prediction: NULL)."""
    with op.batch_alter_table('calibration', schema=None) as batch_op:
        batch_op.add_column(sa.Column('predicted_error_m', sa.Float(), nullable=True))


def downgrade() -> None:
    """Undo this revision (the predictions stay in each calibration's diagnostics)."""
    with op.batch_alter_table('calibration', schema=None) as batch_op:
        batch_op.drop_column('predicted_error_m')
