"""cube_check.height_judged: whether the edge error counts the cube's height, which is measured
from the platter and is judged only for a cube of the platter's finish

Revision ID: 0014_cube_height_judged
Revises: 0013_cube_check_unmeasured
Create Date: 2026-11-30 04:20:00
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = '0014_cube_height_judged'
down_revision: str | None = '0013_cube_check_unmeasured'
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    """Apply this revision (every check stored before it judged the height: true)."""
    with op.batch_alter_table('cube_check', schema=None) as batch_op:
        batch_op.add_column(sa.Column('height_judged', sa.Boolean(), nullable=False,
                                      server_default=sa.true()))


def downgrade() -> None:
    """Undo this revision."""
    with op.batch_alter_table('cube_check', schema=None) as batch_op:
        batch_op.drop_column('height_judged')
