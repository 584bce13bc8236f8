"""Text to speech refuses, before any work, text in a script its voice cannot read."""

from __future__ import annotations

import pytest

from nvp.errors import NvpError
from nvp.tts import check_speakable, have_piper, synthesize


@pytest.mark.parametrize(
    ("text", "script"),
    [("你好，世界", "CJK"), ("مرحبا بالعالم", "Arabic"), ("Hello 世界", "CJK"), ("Γειά σου", "Greek")],
)
def test_an_english_voice_refuses_words_in_another_script(text, script):
    with pytest.raises(NvpError, match=f"cannot read words in {script} script"):
        check_speakable(text, "en-us", "joe_us")


@pytest.mark.parametrize(
    ("text", "language"),
    [
        ("Hello, café naïve — O'Brien's 42 Zoë!", "en-us"),
        ("Привет, мир (Moscow)", "ru"),
        ("你好 world", "cmn"),
        ("こんにちは世界", "ja"),
        ("ｈｅｌｌｏ", "en_US"),
    ],
)
def test_text_in_the_voices_script_is_spoken(text, language):
    check_speakable(text, language, "v")


@pytest.mark.skipif(not have_piper(), reason="piper is not installed")
def test_synthesize_refuses_chinese_for_the_english_voice_before_speaking(monkeypatch):
    import nvp.tts

    monkeypatch.setattr(nvp.tts, "_piper", lambda *a, **k: pytest.fail("spoke"))
    with pytest.raises(NvpError, match="joe_us .en-us. cannot read words in CJK script"):
        synthesize("我们今天说中文。", engine="piper")


@pytest.mark.skipif(not have_piper(), reason="piper is not installed")
def test_nvp_say_refuses_arabic_text_for_the_english_voice_in_one_line(tmp_path, capsys):
    from nvp.app.cli import main

    code = main(
        ["-q", "say", "مرحبا بالعالم", "--person", str(tmp_path / "p"), "-o", str(tmp_path / "x.mp4")]
    )
    lines = capsys.readouterr().err.splitlines()
    assert code == 2 and len(lines) == 1 and "Arabic script" in lines[0], lines
    assert not list(tmp_path.iterdir())
