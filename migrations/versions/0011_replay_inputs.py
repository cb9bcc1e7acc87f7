"""A particle-filter session keeps what it was given, so its smoothed track can be had by
replaying it (server/estimation/replay.py): the session's opening state and each batch's
steps, scans and the fixes they got. NULL for the other trackers and for what was stored
before (their smoothed track stays the RTS over the stored moments).

Revision ID: 0011_replay_inputs
Revises: 0010_knn_retrain
Create Date: 2026-12-07 05:00:00
"""
import sqlalchemy as sa
from alembic import op

revision = '0011_replay_inputs'
down_revision = '0010_knn_retrain'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('tracking_sessions') as batch_op:
        batch_op.add_column(sa.Column('opening_state', sa.JSON(), nullable=True))
    with op.batch_alter_table('session_batches') as batch_op:
        batch_op.add_column(sa.Column('inputs', sa.JSON(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table('session_batches') as batch_op:
        batch_op.drop_column('inputs')
    with op.batch_alter_table('tracking_sessions') as batch_op:
        batch_op.drop_column('opening_state')
