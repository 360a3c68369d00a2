"""database_identity: a random id per database, naming its run folders and shared copies

Revision ID: 0011_database_identity
Revises: 0010_station_lock
Create Date: 2026-11-28 09:00:00

Two databases that share one CALSTATION_HOME (a damaged one moved aside, any --db) used to
write their runs to the same runs/<run id> folders. New runs now go to runs/<uid>/<run id>; the
runs stored before keep the folder their row records.
"""

from __future__ import annotations

import datetime as dt
import uuid
from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = '0011_database_identity'
down_revision: str | None = '0010_station_lock'
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    """Apply this revision: the table, and this database's identity in it."""
    table = op.create_table(
        'database_identity',
        sa.Column('id', sa.Integer(), nullable=False),
        sa.Column('uid', sa.String(length=32), nullable=False),
        sa.Column('created_at', sa.DateTime(timezone=True), nullable=False),
        sa.PrimaryKeyConstraint('id', name=op.f('pk_database_identity')),
        sa.UniqueConstraint('uid', name=op.f('uq_database_identity_uid')),
    )
    op.bulk_insert(table, [{'id': 1, 'uid': uuid.uuid4().hex[:12],
                            'created_at': dt.datetime.now(dt.UTC)}])


def downgrade() -> None:
    """Undo this revision (the runs keep the folders their rows record)."""
    op.drop_table('database_identity')
