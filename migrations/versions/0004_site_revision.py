"""site revision: one value that changes with anything a fix depends on; sessions by owner

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
    op.create_index('ix_tracking_sessions_owner_created', 'tracking_sessions', ['owner_key', 'created_at'])


def downgrade() -> None:
    op.drop_index('ix_tracking_sessions_owner_created', table_name='tracking_sessions')
    with op.batch_alter_table('sites', schema=None) as batch_op:
        batch_op.drop_column('revision')
