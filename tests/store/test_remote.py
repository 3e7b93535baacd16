"""Object stores: URL dispatch, and one contract (put, head, multipart, abort, read-back) for local and S3."""

from __future__ import annotations

import hashlib
from collections.abc import Iterator
from pathlib import Path

import pytest

from telerig.errors import ConfigError
from telerig.store.remote import (
    LocalObjectStore,
    ObjectStore,
    RemoteConfig,
    S3ObjectStore,
    UploadError,
    multipart_etag,
    open_store,
)

_MiB = 1 << 20


def test_open_store_picks_s3_for_s3_urls() -> None:
    store = open_store(RemoteConfig(url="s3://bucket/some/prefix", endpoint_url="http://127.0.0.1:1"))
    assert isinstance(store, S3ObjectStore)
    assert store.url == "s3://bucket/some/prefix"
    assert store.url_for("ep-1/manifest.json") == "s3://bucket/some/prefix/ep-1/manifest.json"


def test_open_store_picks_a_local_directory_for_paths_and_file_urls(tmp_path: Path) -> None:
    by_path = open_store(str(tmp_path / "a"))
    by_url = open_store((tmp_path / "b").as_uri())
    assert isinstance(by_path, LocalObjectStore)
    assert isinstance(by_url, LocalObjectStore)
    assert by_url.root == tmp_path / "b"


def test_open_store_rejects_unknown_schemes_naming_the_supported_ones() -> None:
    with pytest.raises(ConfigError, match=r"unsupported scheme 'gs'.*Available: s3, file"):
        open_store("gs://bucket/x")


def test_s3_url_without_a_bucket_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match="s3://bucket/prefix"):
        S3ObjectStore(RemoteConfig(url="s3:///prefix"))


def test_keys_must_be_relative_paths(tmp_path: Path) -> None:
    store = LocalObjectStore(tmp_path)
    with pytest.raises(ValueError, match="relative"):
        store.put("../escape", b"x", sha256="0")


def test_s3_parts_default_to_the_aws_minimum() -> None:
    assert S3ObjectStore(RemoteConfig(url="s3://bucket/x")).min_part_size == 5 * _MiB


@pytest.fixture(params=["local", "s3"])
def store(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[ObjectStore]:
    if request.param == "local":
        made: ObjectStore = LocalObjectStore(tmp_path / "remote")
        made.min_part_size = 1024
    else:
        made = S3ObjectStore(request.getfixturevalue("s3_config"))
    made.check()
    yield made
    made.close()


def test_put_then_head_reports_size_and_sha256(store: ObjectStore) -> None:
    data = b"hello episode"
    sha = hashlib.sha256(data).hexdigest()
    store.put("ep/a.bin", data, sha256=sha)
    info = store.head("ep/a.bin")
    assert info is not None
    assert (info.size, info.sha256) == (len(data), sha)
    assert store.read_sha256("ep/a.bin") == sha
    if store.etag_is_md5:
        assert info.etag == hashlib.md5(data).hexdigest()


def test_head_of_a_missing_object_is_none(store: ObjectStore) -> None:
    assert store.head("nope/x") is None


def test_multipart_upload_lists_parts_and_assembles_them_in_order(store: ObjectStore) -> None:
    parts = [bytes([n]) * store.min_part_size for n in (1, 2)] + [b"tail"]
    whole = b"".join(parts)
    sha = hashlib.sha256(whole).hexdigest()
    upload_id = store.begin_multipart("ep/big.bin", sha256=sha)
    etags = [(n, store.put_part("ep/big.bin", upload_id, n, data)) for n, data in enumerate(parts, 1)]
    assert store.list_parts("ep/big.bin", upload_id) == dict(etags)
    store.complete_multipart("ep/big.bin", upload_id, etags)

    info = store.head("ep/big.bin")
    assert info is not None
    assert (info.size, info.sha256) == (len(whole), sha)
    assert store.read_sha256("ep/big.bin") == sha
    if store.etag_is_md5:
        assert info.etag == multipart_etag([hashlib.md5(p).digest() for p in parts])


def test_aborted_multipart_upload_is_gone(store: ObjectStore) -> None:
    upload_id = store.begin_multipart("ep/x.bin", sha256="0" * 64)
    store.put_part("ep/x.bin", upload_id, 1, b"abc")
    store.abort_multipart("ep/x.bin", upload_id)
    assert store.list_parts("ep/x.bin", upload_id) is None
    assert store.head("ep/x.bin") is None


def test_s3_check_names_a_missing_bucket(moto_s3: object) -> None:
    config = moto_s3.config("no-such-bucket")
    with pytest.raises(UploadError, match="no-such-bucket"):
        S3ObjectStore(config).check()


def test_s3_endpoint_comes_from_the_environment_when_not_configured(
    s3_config: RemoteConfig, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("AWS_ENDPOINT_URL_S3", str(s3_config.endpoint_url))
    store = S3ObjectStore(s3_config.model_copy(update={"endpoint_url": None}))
    store.put("k", b"v", sha256=hashlib.sha256(b"v").hexdigest())
    assert store.head("k") is not None
