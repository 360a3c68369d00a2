"""station_lock: one run per station, whatever starts it (who holds it, from where, since when)

Revision ID: 0010_station_lock
Revises: 0009_cube_flatness_excess
Create Date: 2026-11-27 09:00:00
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = '0010_station_lock'
down_revision: str | None = '0009_cube_flatness_excess'
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    """Apply this revision (no station is held)."""
    op.create_table(
        'station_lock',
        sa.Column('station_id', sa.Integer(), nullable=False),
        sa.Column('token', sa.String(length=64), nullable=False),
        sa.Column('run_id', sa.Integer(), nullable=True),
        sa.Column('operator', sa.String(length=100), nullable=False),
        sa.Column('front_end', sa.String(length=300), nullable=False),
        sa.Column('host', sa.String(length=255), nullable=False),
        sa.Column('pid', sa.Integer(), nullable=False),
        sa.Column('process_started', sa.String(length=64), nullable=True),
        sa.Column('acquired_at', sa.DateTime(timezone=True), nullable=False),
        sa.Column('heartbeat_at', sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(['run_id'], ['run.id'],
                                name=op.f('fk_station_lock_run_id_run'), ondelete='SET NULL'),
        sa.ForeignKeyConstraint(['station_id'], ['station.id'],
                                name=op.f('fk_station_lock_station_id_station'),
                                ondelete='CASCADE'),
        sa.PrimaryKeyConstraint('station_id', name=op.f('pk_station_lock')),
    )


def downgrade() -> None:
    """Undo this revision (a lock held now is forgotten: stop the station's runs first)."""
    op.drop_table('station_lock')
