"""campaign and campaign_run (calstation reprocess), artifact.location (the shared copy's URL)

Revision ID: 0008_campaigns_locations
Revises: 0007_calibration_predicted_error
Create Date: 2026-11-26 20:45:00
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = '0008_campaigns_locations'
down_revision: str | None = '0007_calibration_predicted_error'
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    """Apply this revision (existing artifacts have no shared copy yet: NULL)."""
    op.create_table('campaign',
    sa.Column('id', sa.Integer(), nullable=False),
    sa.Column('key', sa.String(length=64), nullable=False),
    sa.Column('selection', sa.JSON(), nullable=False),
    sa.Column('strategy', sa.String(length=50), nullable=True),
    sa.Column('tolerance', sa.JSON(), nullable=False),
    sa.Column('engine', sa.String(length=100), nullable=False),
    sa.Column('host', sa.String(length=255), nullable=True),
    sa.Column('selected', sa.Integer(), nullable=False),
    sa.Column('started_at', sa.DateTime(timezone=True), nullable=False),
    sa.Column('finished_at', sa.DateTime(timezone=True), nullable=True),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_campaign'))
    )
    with op.batch_alter_table('campaign', schema=None) as batch_op:
        batch_op.create_index(batch_op.f('ix_campaign_key'), ['key'], unique=False)

    op.create_table('campaign_run',
    sa.Column('id', sa.Integer(), nullable=False),
    sa.Column('campaign_id', sa.Integer(), nullable=False),
    sa.Column('run_id', sa.Integer(), nullable=False),
    sa.Column('calibration_id', sa.Integer(), nullable=True),
    sa.Column('outcome', sa.String(length=16), nullable=False),
    sa.Column('flagged', sa.Boolean(), nullable=False),
    sa.Column('refused', sa.Boolean(), nullable=False),
    sa.Column('comparison', sa.JSON(), nullable=True),
    sa.Column('error', sa.Text(), nullable=True),
    sa.Column('seconds', sa.Float(), nullable=True),
    sa.Column('worker', sa.String(length=255), nullable=True),
    sa.Column('created_at', sa.DateTime(timezone=True), nullable=False),
    sa.ForeignKeyConstraint(['calibration_id'], ['calibration.id'], name=op.f('fk_campaign_run_calibration_id_calibration'), ondelete='SET NULL'),
    sa.ForeignKeyConstraint(['campaign_id'], ['campaign.id'], name=op.f('fk_campaign_run_campaign_id_campaign'), ondelete='CASCADE'),
    sa.ForeignKeyConstraint(['run_id'], ['run.id'], name=op.f('fk_campaign_run_run_id_run'), ondelete='CASCADE'),
    sa.PrimaryKeyConstraint('id', name=op.f('pk_campaign_run')),
    sa.UniqueConstraint('campaign_id', 'run_id', name=op.f('uq_campaign_run_campaign_id_run_id'))
    )
    with op.batch_alter_table('campaign_run', schema=None) as batch_op:
        batch_op.create_index(batch_op.f('ix_campaign_run_campaign_id'), ['campaign_id'], unique=False)
        batch_op.create_index(batch_op.f('ix_campaign_run_flagged'), ['flagged'], unique=False)
        batch_op.create_index(batch_op.f('ix_campaign_run_run_id'), ['run_id'], unique=False)

    with op.batch_alter_table('artifact', schema=None) as batch_op:
        batch_op.add_column(sa.Column('location', sa.String(length=1000), nullable=True))



def downgrade() -> None:
    """Undo this revision: the campaigns' rows and the shared copies' locations are dropped
    (the re-processings stay as ``calibration`` rows of stage ``reprocess``; the files stay where
    they are, and ``calstation upload`` finds them there again, verified)."""
    with op.batch_alter_table('artifact', schema=None) as batch_op:
        batch_op.drop_column('location')

    with op.batch_alter_table('campaign_run', schema=None) as batch_op:
        batch_op.drop_index(batch_op.f('ix_campaign_run_run_id'))
        batch_op.drop_index(batch_op.f('ix_campaign_run_flagged'))
        batch_op.drop_index(batch_op.f('ix_campaign_run_campaign_id'))

    op.drop_table('campaign_run')
    with op.batch_alter_table('campaign', schema=None) as batch_op:
        batch_op.drop_index(batch_op.f('ix_campaign_key'))

    op.drop_table('campaign')
