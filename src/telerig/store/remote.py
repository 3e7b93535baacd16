"""Where uploaded episodes live: a local directory or S3-compatible object storage (s3fs), by URL."""

from __future__ import annotations

import base64
import contextlib
import hashlib
import importlib
import logging
import os
import secrets
import shutil
from abc import ABC, abstractmethod
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import unquote, urlparse

from pydantic import BaseModel, ConfigDict, Field, SecretStr

from telerig.errors import ChecksumMismatchError, ConfigError, DependencyError, UploadError

__all__ = [
    "ChecksumMismatchError",
    "LocalObjectStore",
    "ObjectInfo",
    "ObjectStore",
    "RemoteConfig",
    "S3ObjectStore",
    "UploadError",
    "multipart_etag",
    "open_store",
]

_log = logging.getLogger("telerig.store.remote")

_MiB = 1 << 20
#: S3 refuses parts smaller than this (except the last one) [bytes].
S3_MIN_PART = 5 * _MiB
_READ_BLOCK = _MiB
_SHA256_META = "sha256"


class RemoteConfig(BaseModel):
    """Where uploads go and how to reach it.

    Attributes:
        url: ``s3://bucket/prefix`` for object storage; a path or ``file:///path`` for a local
            directory (another disk, an NFS mount).
        endpoint_url: S3 endpoint for S3-compatible services (MinIO, Ceph, moto); ``None``: the
            ``AWS_ENDPOINT_URL_S3`` / ``AWS_ENDPOINT_URL`` environment variables, else AWS.
        access_key_id: ``None``: the standard AWS chain (``AWS_ACCESS_KEY_ID``, ``~/.aws``, ...).
        secret_access_key: ``None``: the standard AWS chain (``AWS_SECRET_ACCESS_KEY``, ...).
        region: ``None``: ``AWS_DEFAULT_REGION`` / ``AWS_REGION``, else ``us-east-1``.
        etag_is_md5: The backend returns MD5 ETags (AWS without SSE-KMS, MinIO, Ceph, moto);
            uploads then check every part and the assembled object against local MD5s.
        min_part_size: Smallest multipart part the backend accepts, except the last [bytes];
            5 MiB on AWS and most S3-compatible services (test servers may allow less).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    url: str = Field(min_length=1)
    endpoint_url: str | None = None
    access_key_id: str | None = None
    secret_access_key: SecretStr | None = None
    region: str | None = None
    etag_is_md5: bool = True
    min_part_size: int = Field(default=S3_MIN_PART, ge=1)


@dataclass(frozen=True, slots=True)
class ObjectInfo:
    """What the store knows of one object without reading it.

    Attributes:
        size: Size [bytes].
        sha256: Hex SHA-256 recorded with the object at upload (object metadata); ``None`` if absent.
        etag: Backend ETag without quotes (MD5 hex, or ``md5-of-md5s-N`` for multipart); ``None``
            where the backend has none (local directory).
    """

    size: int
    sha256: str | None
    etag: str | None


def multipart_etag(part_md5s: Sequence[bytes]) -> str:
    """The ETag S3 gives an object assembled from parts with these raw MD5 digests (16 bytes each)."""
    return f"{hashlib.md5(b''.join(part_md5s)).hexdigest()}-{len(part_md5s)}"


class ObjectStore(ABC):
    """Objects under one base URL, addressed by ``/``-separated keys relative to it.

    Writes are whole objects (:meth:`put`) or multipart uploads that survive a crash of the
    writer (:meth:`begin_multipart` ... :meth:`complete_multipart`): parts already stored are
    listed by :meth:`list_parts` and need not be sent again.
    """

    #: The minimum size of a part other than the last [bytes].
    min_part_size: int = 1
    #: Whether :attr:`ObjectInfo.etag` and part ETags are MD5s of the content.
    etag_is_md5: bool = False

    @property
    @abstractmethod
    def url(self) -> str:
        """The base URL."""

    def url_for(self, key: str) -> str:
        """URL of ``key`` (an object or a ``/``-prefix)."""
        return f"{self.url.rstrip('/')}/{key}"

    def check(self) -> None:  # noqa: B027 - optional hook, nothing to check by default
        """Raise :class:`UploadError` with the fix if the store cannot be written (no bucket...)."""

    @abstractmethod
    def head(self, key: str) -> ObjectInfo | None:
        """Size, recorded sha256 and ETag of ``key``; ``None`` if it does not exist."""

    @abstractmethod
    def put(self, key: str, data: bytes, *, sha256: str) -> str:
        """Store ``data`` at ``key`` with its hex ``sha256`` recorded; returns the ETag (or ``""``)."""

    @abstractmethod
    def begin_multipart(self, key: str, *, sha256: str) -> str:
        """Start a multipart upload of ``key`` whose content has hex ``sha256``; returns its id."""

    @abstractmethod
    def list_parts(self, key: str, upload_id: str) -> dict[int, str] | None:
        """Parts stored so far, part number (from 1) -> ETag; ``None`` if the upload is gone."""

    @abstractmethod
    def put_part(self, key: str, upload_id: str, number: int, data: bytes) -> str:
        """Store part ``number`` (from 1) of an upload; returns its ETag."""

    @abstractmethod
    def complete_multipart(self, key: str, upload_id: str, parts: Sequence[tuple[int, str]]) -> None:
        """Assemble the object from ``(number, etag)`` parts in order."""

    @abstractmethod
    def abort_multipart(self, key: str, upload_id: str) -> None:
        """Drop an unfinished upload and its parts (no error if it is already gone)."""

    @abstractmethod
    def read_sha256(self, key: str) -> str:
        """Read ``key`` back and return the hex SHA-256 of its content."""

    def close(self) -> None:  # noqa: B027 - optional hook
        """Release connections; idempotent."""


def _md5_b64(data: bytes) -> str:
    return base64.b64encode(hashlib.md5(data).digest()).decode("ascii")


def _check_key(key: str) -> None:
    parts = key.split("/")
    if not key or key.startswith("/") or any(p in ("", ".", "..") for p in parts):
        raise ValueError(f"object key {key!r} must be a relative '/'-separated path without '.' or '..'")


class LocalObjectStore(ObjectStore):
    """Objects as files under a directory; written to a temporary name, fsynced, then renamed.

    Multipart uploads keep their parts in ``<root>/.multipart/<upload id>/`` until completed.
    The recorded sha256 is not stored: :meth:`head` hashes the file (local disk is cheap to read).
    """

    def __init__(self, root: Path | str) -> None:
        """Store under directory ``root`` (created on the first write)."""
        self._root = Path(root).absolute()

    @property
    def url(self) -> str:
        return self._root.as_uri()

    @property
    def root(self) -> Path:
        """The directory."""
        return self._root

    def check(self) -> None:
        try:
            self._root.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise UploadError(f"cannot create upload directory {self._root}: {exc.strerror}") from None
        if not os.access(self._root, os.W_OK):
            raise UploadError(f"upload directory {self._root} is not writable; fix its permissions")

    def _path(self, key: str) -> Path:
        _check_key(key)
        return self._root / key

    def head(self, key: str) -> ObjectInfo | None:
        path = self._path(key)
        if not path.is_file():
            return None
        return ObjectInfo(size=path.stat().st_size, sha256=self.read_sha256(key), etag=None)

    def put(self, key: str, data: bytes, *, sha256: str) -> str:
        path = self._path(key)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{secrets.token_hex(4)}.tmp")
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        return ""

    def _parts_dir(self, upload_id: str) -> Path:
        if not upload_id.isalnum():
            raise ValueError(f"upload id {upload_id!r} is not one this store made")
        return self._root / ".multipart" / upload_id

    def begin_multipart(self, key: str, *, sha256: str) -> str:
        self._path(key)
        upload_id = secrets.token_hex(8)
        directory = self._parts_dir(upload_id)
        directory.mkdir(parents=True)
        (directory / "key").write_text(key, encoding="utf-8")
        return upload_id

    def list_parts(self, key: str, upload_id: str) -> dict[int, str] | None:
        directory = self._parts_dir(upload_id)
        if not (directory / "key").is_file() or (directory / "key").read_text(encoding="utf-8") != key:
            return None
        return {
            int(p.name): hashlib.md5(p.read_bytes()).hexdigest()
            for p in directory.iterdir()
            if p.name.isdigit()
        }

    def put_part(self, key: str, upload_id: str, number: int, data: bytes) -> str:
        directory = self._parts_dir(upload_id)
        if not directory.is_dir():
            raise UploadError(f"multipart upload {upload_id} of {key} is gone; start the upload again")
        tmp = directory / f"{number}.tmp"
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, directory / str(number))
        return hashlib.md5(data).hexdigest()

    def complete_multipart(self, key: str, upload_id: str, parts: Sequence[tuple[int, str]]) -> None:
        directory = self._parts_dir(upload_id)
        path = self._path(key)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{upload_id}.tmp")
        with open(tmp, "wb") as out:
            for number, _etag in parts:
                with open(directory / str(number), "rb") as part:
                    shutil.copyfileobj(part, out, _READ_BLOCK)
            out.flush()
            os.fsync(out.fileno())
        os.replace(tmp, path)
        shutil.rmtree(directory, ignore_errors=True)

    def abort_multipart(self, key: str, upload_id: str) -> None:
        shutil.rmtree(self._parts_dir(upload_id), ignore_errors=True)

    def read_sha256(self, key: str) -> str:
        digest = hashlib.sha256()
        with open(self._path(key), "rb") as f:
            while block := f.read(_READ_BLOCK):
                digest.update(block)
        return digest.hexdigest()


def _import_s3fs() -> Any:
    try:
        return importlib.import_module("s3fs")
    except ImportError:
        raise DependencyError("s3:// storage needs s3fs; install it with `pip install s3fs`") from None


class S3ObjectStore(ObjectStore):
    """Objects in an S3 bucket under a prefix, through s3fs (aiobotocore).

    Every request that carries data sends its Content-MD5, so the server rejects bytes damaged on
    the way; every object records the manifest sha256 as ``x-amz-meta-sha256``.
    """

    def __init__(self, config: RemoteConfig) -> None:
        """Connect lazily to the bucket and prefix of ``config.url`` (``s3://bucket/prefix``)."""
        parsed = urlparse(config.url)
        if parsed.scheme != "s3" or not parsed.netloc:
            raise ConfigError(f"S3 url {config.url!r} must look like s3://bucket/prefix")
        self._bucket = parsed.netloc
        self._prefix = parsed.path.strip("/")
        self._config = config
        self.etag_is_md5 = config.etag_is_md5
        self.min_part_size = config.min_part_size
        endpoint = (
            config.endpoint_url or os.environ.get("AWS_ENDPOINT_URL_S3") or os.environ.get("AWS_ENDPOINT_URL")
        )
        region = (
            config.region
            or os.environ.get("AWS_DEFAULT_REGION")
            or os.environ.get("AWS_REGION")
            or "us-east-1"
        )
        s3fs = _import_s3fs()
        secret = config.secret_access_key.get_secret_value() if config.secret_access_key else None
        self._fs: Any = s3fs.S3FileSystem(
            key=config.access_key_id,
            secret=secret,
            endpoint_url=endpoint,
            client_kwargs={"region_name": region},
            skip_instance_cache=True,
        )
        self._endpoint = endpoint or "AWS"

    @property
    def url(self) -> str:
        return f"s3://{self._bucket}/{self._prefix}" if self._prefix else f"s3://{self._bucket}"

    @property
    def bucket(self) -> str:
        """The bucket name."""
        return self._bucket

    def _key(self, key: str) -> str:
        _check_key(key)
        return f"{self._prefix}/{key}" if self._prefix else key

    @contextlib.contextmanager
    def _errors(self, what: str) -> Iterator[None]:
        try:
            yield
        except FileNotFoundError as exc:
            raise UploadError(
                f"{what} at {self._endpoint}: not found ({exc}); check that bucket {self._bucket!r} exists"
            ) from None
        except PermissionError as exc:
            raise UploadError(
                f"{what} at {self._endpoint}: access denied ({exc}); check the credentials"
            ) from None
        except (OSError, ValueError) as exc:
            raise UploadError(f"{what} at {self._endpoint}: {exc}") from None

    def _call(self, method: str, what: str, **kwargs: Any) -> Any:
        with self._errors(what):
            return self._fs.call_s3(method, Bucket=self._bucket, **kwargs)

    def check(self) -> None:
        self._call("head_bucket", f"cannot reach bucket {self._bucket!r}")

    def head(self, key: str) -> ObjectInfo | None:
        try:
            out = self._fs.call_s3("head_object", Bucket=self._bucket, Key=self._key(key))
        except FileNotFoundError:
            return None
        except (OSError, ValueError) as exc:
            raise UploadError(f"cannot look up {self.url_for(key)} at {self._endpoint}: {exc}") from None
        meta = {k.lower(): v for k, v in (out.get("Metadata") or {}).items()}
        etag = out.get("ETag")
        return ObjectInfo(
            size=int(out["ContentLength"]),
            sha256=meta.get(_SHA256_META),
            etag=etag.strip('"') if etag else None,
        )

    def put(self, key: str, data: bytes, *, sha256: str) -> str:
        out = self._call(
            "put_object",
            f"cannot upload {self.url_for(key)}",
            Key=self._key(key),
            Body=data,
            ContentMD5=_md5_b64(data),
            Metadata={_SHA256_META: sha256},
        )
        return str(out.get("ETag", "")).strip('"')

    def begin_multipart(self, key: str, *, sha256: str) -> str:
        out = self._call(
            "create_multipart_upload",
            f"cannot start uploading {self.url_for(key)}",
            Key=self._key(key),
            Metadata={_SHA256_META: sha256},
        )
        return str(out["UploadId"])

    def list_parts(self, key: str, upload_id: str) -> dict[int, str] | None:
        parts: dict[int, str] = {}
        marker = 0
        while True:
            try:
                out = self._fs.call_s3(
                    "list_parts",
                    Bucket=self._bucket,
                    Key=self._key(key),
                    UploadId=upload_id,
                    PartNumberMarker=marker,
                )
            except FileNotFoundError:  # NoSuchUpload: completed, aborted or expired
                return None
            except (OSError, ValueError) as exc:
                raise UploadError(
                    f"cannot list parts of {self.url_for(key)} at {self._endpoint}: {exc}"
                ) from None
            for part in out.get("Parts", []):
                parts[int(part["PartNumber"])] = str(part["ETag"]).strip('"')
            if not out.get("IsTruncated"):
                return parts
            marker = int(out["NextPartNumberMarker"])

    def put_part(self, key: str, upload_id: str, number: int, data: bytes) -> str:
        out = self._call(
            "upload_part",
            f"cannot upload part {number} of {self.url_for(key)}",
            Key=self._key(key),
            UploadId=upload_id,
            PartNumber=number,
            Body=data,
            ContentMD5=_md5_b64(data),
        )
        return str(out["ETag"]).strip('"')

    def complete_multipart(self, key: str, upload_id: str, parts: Sequence[tuple[int, str]]) -> None:
        self._call(
            "complete_multipart_upload",
            f"cannot complete {self.url_for(key)}",
            Key=self._key(key),
            UploadId=upload_id,
            MultipartUpload={"Parts": [{"PartNumber": n, "ETag": f'"{etag}"'} for n, etag in parts]},
        )

    def abort_multipart(self, key: str, upload_id: str) -> None:
        with contextlib.suppress(FileNotFoundError):
            self._fs.call_s3(
                "abort_multipart_upload", Bucket=self._bucket, Key=self._key(key), UploadId=upload_id
            )

    def read_sha256(self, key: str) -> str:
        digest = hashlib.sha256()
        with (
            self._errors(f"cannot read back {self.url_for(key)}"),
            self._fs.open(f"{self._bucket}/{self._key(key)}", "rb", block_size=8 * _MiB) as f,
        ):
            while block := f.read(8 * _MiB):
                digest.update(block)
        return digest.hexdigest()


def open_store(config: RemoteConfig | str) -> ObjectStore:
    """The object store for ``config`` (or a bare URL): ``s3://`` -> :class:`S3ObjectStore`, else local.

    Raises:
        ConfigError: The URL scheme is not supported.
    """
    cfg = RemoteConfig(url=config) if isinstance(config, str) else config
    parsed = urlparse(cfg.url)
    if parsed.scheme == "s3":
        return S3ObjectStore(cfg)
    if parsed.scheme == "file":
        return LocalObjectStore(unquote(parsed.path))
    if parsed.scheme == "" or (len(parsed.scheme) == 1 and os.name == "nt"):
        return LocalObjectStore(cfg.url)
    raise ConfigError(
        f"storage url {cfg.url!r} has unsupported scheme {parsed.scheme!r}. Available: s3, file"
    )
