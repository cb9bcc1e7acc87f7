"""survey uploads remember their request's hash and the file rows they stored

Revision ID: 0005_upload_requests
Revises: 0004_site_revision
Create Date: 2026-12-01 12:20:00
"""
from alembic import op
import sqlalchemy as sa

revision = '0005_upload_requests'
down_revision = '0004_site_revision'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('survey_uploads', schema=None) as batch_op:
        batch_op.add_column(sa.Column('request_hash', sa.String(length=64), nullable=True))
        batch_op.add_column(sa.Column('source', sa.String(length=200), nullable=True))
        batch_op.add_column(sa.Column('source_rows', sa.JSON(), nullable=True))
    op.create_index('ix_survey_uploads_source', 'survey_uploads', ['site_id', 'source'])


def downgrade() -> None:
    op.drop_index('ix_survey_uploads_source', table_name='survey_uploads')
    with op.batch_alter_table('survey_uploads', schema=None) as batch_op:
        batch_op.drop_column('source_rows')
        batch_op.drop_column('source')
        batch_op.drop_column('request_hash')
