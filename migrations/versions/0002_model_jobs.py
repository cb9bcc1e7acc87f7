"""model jobs

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-25 00:07:07.042432
"""
from alembic import op
import sqlalchemy as sa

revision = '0002'
down_revision = '0001'
branch_labels = None
depends_on = None

def upgrade() -> None:
    with op.batch_alter_table('models', schema=None) as batch_op:
        batch_op.add_column(sa.Column('include_crowd', sa.Boolean(), nullable=False, server_default=sa.true()))
        batch_op.add_column(sa.Column('claimed_at', sa.DateTime(timezone=True), nullable=True))
        batch_op.create_index('uq_models_one_active', ['site_id'], unique=True, sqlite_where=sa.text('active'), postgresql_where=sa.text('active'))

def downgrade() -> None:
    with op.batch_alter_table('models', schema=None) as batch_op:
        batch_op.drop_index('uq_models_one_active', sqlite_where=sa.text('active'), postgresql_where=sa.text('active'))
        batch_op.drop_column('claimed_at')
        batch_op.drop_column('include_crowd')

