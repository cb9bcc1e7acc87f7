"""`knn` is now built on wknn's search (server/estimation/fingerprint/knn.py): a stored knn
artifact of the previous form cannot be loaded, so every ready knn model goes back to the
queue and the training worker fits it again on the site's fingerprints, keeping its id and
whether it is the site's active model (the retrain asks for activation `always` when it was
active, `never` when not). No schema change; the downgrade leaves the retrained models as
they are.

Revision ID: 0010_knn_retrain
Revises: 0009_track_states
Create Date: 2026-12-03 08:00:00
"""
import sqlalchemy as sa
from alembic import op

revision = '0010_knn_retrain'
down_revision = '0009_track_states'
branch_labels = None
depends_on = None

models = sa.table('models', sa.column('id', sa.Integer), sa.column('algorithm', sa.String), sa.column('status', sa.String),
                  sa.column('active', sa.Boolean), sa.column('metrics', sa.JSON), sa.column('error', sa.Text),
                  sa.column('claimed_at', sa.DateTime))
artifacts = sa.table('model_artifacts', sa.column('model_id', sa.Integer))


def upgrade() -> None:
    conn = op.get_bind()
    ready = conn.execute(sa.select(models.c.id, models.c.active)
                         .where(models.c.algorithm == 'knn', models.c.status == 'ready')).all()
    for model_id, active in ready:
        conn.execute(sa.delete(artifacts).where(artifacts.c.model_id == model_id))
        conn.execute(sa.update(models).where(models.c.id == model_id).values(
            status='queued', error=None, claimed_at=None,
            metrics={"activation": {"requested": "always" if active else "never"}}))


def downgrade() -> None:
    pass
