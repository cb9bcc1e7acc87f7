"""Buildings: a site may hold several buildings, and a floor is a (building, level) pair

Adds ``building`` (0 for every existing row, so a v1 site is building 0) to floors,
fingerprints, reference points, transmitters (NULL where the floor is NULL) and track
estimates; floors become unique per (site, building, level) and reference points per
(site, building, floor, key). Adds ``floors.walkable`` (optional walkable polygons in site
metres) and an index on tracking_sessions (created_at, id) for the admin session lists.

The old unique constraints were created unnamed: PostgreSQL named them itself (looked up
here), SQLite keeps no name (a naming convention names them for the batch rebuild). The
downgrade fails on a site holding the same level in two buildings rather than drop rows.

Revision ID: 0008_buildings
Revises: 0007_models_autoincrement
Create Date: 2026-12-01 14:15:00
"""
import sqlalchemy as sa
from alembic import op

revision = '0008_buildings'
down_revision = '0007_models_autoincrement'
branch_labels = None
depends_on = None

#: names the unnamed unique constraints that SQLite reflects, so the batch rebuild can drop them
_SQLITE_NAMES = {"uq": "uq_%(table_name)s_%(column_0_name)s"}
_BUILDING_NOT_NULL = ('fingerprints', 'track_estimates')


def _unique_name(table: str, columns: list[str]) -> str:
    """The name of the unique constraint on exactly ``columns`` (named by convention on SQLite)."""
    for uq in sa.inspect(op.get_bind()).get_unique_constraints(table):
        if list(uq["column_names"]) == columns:
            return uq["name"] or f"uq_{table}_{columns[0]}"
    raise RuntimeError(f"no unique constraint on {table} {columns}")


def _swap_unique(table: str, old: list[str], new_name: str, new: list[str], *, adding: bool,
                 other: sa.Column | None = None) -> None:
    """Add (or drop) ``building`` and ``other`` and swap the table's unique constraint, in one rebuild."""
    old_name = _unique_name(table, old)
    with op.batch_alter_table(table, naming_convention=_SQLITE_NAMES) as batch_op:
        if adding:
            batch_op.add_column(sa.Column('building', sa.Integer(), nullable=False, server_default='0'))
            if other is not None:
                batch_op.add_column(other)
        batch_op.drop_constraint(old_name, type_='unique')
        batch_op.create_unique_constraint(new_name, new)
        if not adding:
            batch_op.drop_column('building')
            if other is not None:
                batch_op.drop_column(other.name)


def upgrade() -> None:
    _swap_unique('floors', ['site_id', 'level'], 'uq_floors_site_building_level',
                 ['site_id', 'building', 'level'], adding=True,
                 other=sa.Column('walkable', sa.JSON(), nullable=True))
    _swap_unique('reference_points', ['site_id', 'floor', 'key'], 'uq_reference_points_site_building_floor_key',
                 ['site_id', 'building', 'floor', 'key'], adding=True)
    for table in _BUILDING_NOT_NULL:
        with op.batch_alter_table(table) as batch_op:
            batch_op.add_column(sa.Column('building', sa.Integer(), nullable=False, server_default='0'))
    with op.batch_alter_table('transmitters') as batch_op:
        batch_op.add_column(sa.Column('building', sa.Integer(), nullable=True))
    op.execute("UPDATE transmitters SET building = 0 WHERE floor IS NOT NULL")
    with op.batch_alter_table('tracking_sessions') as batch_op:
        batch_op.create_index('ix_tracking_sessions_created_id', ['created_at', 'id'], unique=False)


def downgrade() -> None:
    with op.batch_alter_table('tracking_sessions') as batch_op:
        batch_op.drop_index('ix_tracking_sessions_created_id')
    for table in ('transmitters', *_BUILDING_NOT_NULL):
        with op.batch_alter_table(table) as batch_op:
            batch_op.drop_column('building')
    _swap_unique('reference_points', ['site_id', 'building', 'floor', 'key'], 'reference_points_site_id_floor_key_key',
                 ['site_id', 'floor', 'key'], adding=False)
    _swap_unique('floors', ['site_id', 'building', 'level'], 'floors_site_id_level_key',
                 ['site_id', 'level'], adding=False, other=sa.Column('walkable', sa.JSON(), nullable=True))
