# monoloc: the two commands are `make demo` and `make test`.
PYTHON ?= python3.11
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: install test test-postgres lint bench demo clean chromium system-deps

$(PY):
	$(PYTHON) -m venv $(VENV) || python3 -m venv $(VENV)
	$(PY) -m pip install --upgrade pip setuptools wheel >/dev/null

$(STAMP): $(PY) pyproject.toml
	$(PY) -m pip install -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

lint: install
	$(VENV)/bin/ruff check .

# The console's browser tests drive Debian's chromium (no browser download).
chromium:
	@test -x /usr/bin/chromium || { $(SUDO) apt-get update -q && \
	  DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -q chromium; }


# The tests start a throwaway PostgreSQL (initdb/pg_ctl, tests/pg_cluster.py) and check the
# nginx config of docker/ with `nginx -t`, and validate docker/compose.yaml with compose (the
# docker plugin, else Debian's docker-compose); the shard suites (tests/shards) need PostGIS
# and pg_auto_failover for that server's version: install Debian's packages when missing.
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)
system-deps:
	@need=""; \
	command -v pg_ctl >/dev/null || ls /usr/lib/postgresql/*/bin/pg_ctl >/dev/null 2>&1 \
	  || need="$$need postgresql"; \
	command -v nginx >/dev/null || [ -x /usr/sbin/nginx ] || need="$$need nginx-light"; \
	pg=$$(ls /usr/lib/postgresql 2>/dev/null | sort -n | tail -1); pg=$${pg:-15}; \
	ls /usr/share/postgresql/$$pg/extension/postgis.control >/dev/null 2>&1 \
	  || need="$$need postgresql-$$pg-postgis-3"; \
	command -v pg_autoctl >/dev/null || need="$$need postgresql-$$pg-auto-failover"; \
	{ docker compose version >/dev/null 2>&1 || command -v docker-compose >/dev/null; } \
	  || need="$$need docker-compose"; \
	if [ -n "$$need" ]; then \
	  echo "installing Debian packages:$$need"; \
	  $(SUDO) apt-get update -qq && DEBIAN_FRONTEND=noninteractive \
	    $(SUDO) apt-get install -y -qq --no-install-recommends $$need >/dev/null; \
	fi


# Two pytest workers (pytest-xdist), one test file each at a time so that a module's
# expensive fixture (a generated city, a built map) is made once: on 2 cores about
# 9 minutes instead of 13. `make test TEST_WORKERS=0` runs the suite in one process.
TEST_WORKERS ?= 2
test: install lint chromium system-deps
	$(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadfile --durations=15

# The storage and ingestion suites against PostgreSQL: a fresh database per test on the
# server of MONOLOC_TEST_POSTGRES_URL (its user must be allowed to create databases).
test-postgres: install
	@test -n "$$MONOLOC_TEST_POSTGRES_URL" || { echo "set MONOLOC_TEST_POSTGRES_URL, e.g. postgresql+psycopg://postgres@/postgres?host=/tmp&port=5432"; exit 2; }
	$(PY) -m pip install -q -e '.[dev,postgres]'
	$(PY) -m pytest -q tests/server/storage tests/server/ingest

demo: install
	$(VENV)/bin/monoloc demo

# Benchmarks: slow test suites, then every bench script (each prints its figures beside a
# baseline and writes bench/results/*.json), then bench/REPORT.md from those results.
BENCHES := vision filter sim ingest localize pnp_calibration retrieval speed accuracy pose_covariance crash load footprint geopose hostile http_overhead formats joint joint_refit error_split transfer mpc lens frame_cost scale

bench: install
	$(PY) -m pytest -q -m slow
	@for b in $(BENCHES); do \
	  if [ -f bench/$$b.py ]; then echo "== bench/$$b.py"; $(PY) -m bench.$$b || exit 1; fi; \
	done
	$(PY) -m bench.accuracy --scenario indoor --size small
	$(PY) -m bench.accuracy --scenario fleet --size small --frames 150
	$(PY) -m bench.closed_loop --scenario indoor
	$(PY) -m bench.closed_loop --scenario urban
	$(PY) -m bench.load --replicas 1 --runs http http-honours --overloads 3 5 \
	  --duration 12 --slices 4 --out bench/results/load_overload.json
	$(PY) -m bench.load --replicas 1 --runs http http-honours --overloads 3 5 --front nginx \
	  --duration 12 --slices 4 --out bench/results/load_overload_nginx.json
	$(PY) -m bench.report

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache
