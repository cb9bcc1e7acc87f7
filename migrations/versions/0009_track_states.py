"""Track estimates keep a self-calibrating tracker's whole state (mean [x, y, b, s], its
covariance, the step that predicted it) for the smoother over the whole state; NULL for the
other trackers and for estimates stored before.

Revision ID: 0009_track_states
Revises: 0008_buildings
Create Date: 2026-12-02 10:40:00
"""
import sqlalchemy as sa
from alembic import op

revision = '0009_track_states'
down_revision = '0008_buildings'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('track_estimates') as batch_op:
        batch_op.add_column(sa.Column('state', sa.JSON(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table('track_estimates') as batch_op:
        batch_op.drop_column('state')
