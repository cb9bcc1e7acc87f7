"""site revision: one value that changes with anything a fix depends on

Revision ID: 0004_site_revision
Revises: 0003_tracking
Create Date: 2026-11-25 02:30:00
"""
from alembic import op
import sqlalchemy as sa

revision = '0004_site_revision'
down_revision = '0003_tracking'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('sites', schema=None) as batch_op:
        batch_op.add_column(sa.Column('revision', sa.String(length=32), server_default='', nullable=False))


def downgrade() -> None:
    with op.batch_alter_table('sites', schema=None) as batch_op:
        batch_op.drop_column('revision')
