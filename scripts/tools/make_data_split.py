"""Write ``scripts/data_split.json``: the fixed train / validation / test split of the real videos by person.

    python -m scripts.tools.make_data_split [--check]

The rule (also written into the file):

1. The unit is the person, never the clip: all clips of one person (as named by CATALOG.md's speaker column,
   e.g. the three StyleTalk Obama clips and EDTalk's uncrop_Obama; VoxCeleb2 id00100's ten clips) are in one
   split. Clips whose catalogue entries could be the same person are kept together (deepavsr 00004 / 00024:
   two bearded BBC interviewees with glasses).
2. People the shipped Audio2ExpressionNet was trained on keep the role they had there (``nvp/assets/
   audio2exp_phonemes.json`` ``split``): its training people are *train*, its validation people (which chose
   its checkpoint) are *validation*. Kristi Noem's MegActor clip, excluded from that training because she was
   a validation person, is *validation* too.
3. Every other person (catalogue batch 2 and later) who is the only person of their language, or whose
   language is unknown, is *test*, so that test measures languages the models never heard (Hindi, Italian,
   Portuguese, French, Cantonese). A language with several people (Mandarin: four) places them by rule 4's
   hash, so that some are heard in training and the others measure unseen people of a language heard there
   (issue 44).
4. The remaining (English) batch-2 people are placed by a hash of their person id:
   ``u = int(sha256(id)[:8], 16) / 16**8``; ``u < 0.5`` test, ``0.5 <= u < 0.7`` validation, else train.

Test people must never be used for training, for choosing checkpoints or settings, or for tuning
thresholds; numbers measured on validation are marked as such. ``video_wide/`` (faces 50-90 px) is not part of
the split: its clips are training material only (the shipped network trains on them); none of its
spokespeople appears in ``video/``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from collections import Counter

from scripts.common import ROOT, SHARED, SPLIT

OUT = SPLIT

# person id -> (language, clips); ids and languages transcribed from CATALOG.md's speaker / language columns
PEOPLE: dict[str, tuple[str, list[str]]] = {
    # batch 1 (the shipped network's data)
    "jim_acosta": ("en", ["dfrf__cnn2_25fps.mp4"]),
    "ted_lieu": ("en", ["edtalk__pose_source2.mp4"]),
    "barack_obama": (
        "en",
        [
            "edtalk__uncrop_Obama.mp4",
            "styletalk__Obama_clip1_av.mp4",
            "styletalk__Obama_clip2_av.mp4",
            "styletalk__Obama_clip3_av.mp4",
        ],
    ),
    "amy_klobuchar": ("en", ["edtalk__mouth_source_av.mp4"]),
    "german_news_anchor": ("de", ["mimictalk__German_20s.mp4"]),
    "fei_fei_li": (
        "en",
        [
            "styletalk__feifeili_clip1_av.mp4",
            "styletalk__feifeili_clip2_short_av.mp4",
            "styletalk__feifeili_clip3_av.mp4",
        ],
    ),
    "kristi_noem": ("en", ["styletalk__KristiNoem_av.mp4", "megactor__audio_CHTF_2.mp4"]),
    "ronald_reagan": ("en", ["styletalk__reagan_clip1_av.mp4"]),
    "latentsync_demo3_man": ("en", ["latentsync__demo3_video.mp4"]),
    "latentsync_demo1_woman": ("en", ["latentsync__demo1_video.mp4"]),
    "alexandria_ocasio_cortez": (
        "en",
        ["sadtalker__WDA_AlexandriaOcasioCortez_000.mp4", "videoretalking__face3.mp4"],
    ),
    "katie_hill": ("en", ["sadtalker__WDA_KatieHill_000.mp4"]),
    "videoretalking_face1_man": ("en", ["videoretalking__face1.mp4"]),
    "eric_swalwell": ("en", ["videoretalking__face2.mp4"]),
    "mairead_mcguinness": ("en", ["videoretalking__face5.mp4"]),
    "kim_presenter": ("en", ["wav2lipgfpgan__kim_7s_raw.mp4"]),
    "jackie_chan": ("en", ["tpsmm__driving.mp4"]),
    "theresa_may": ("en", ["real3dportrait__May_5s.mp4"]),
    "liveportrait_d20_man": ("en", ["liveportrait__d20.mp4"]),
    "megactor_chtf3_woman": ("unknown", ["megactor__audio_CHTF_3.mp4"]),
    "megactor_chtf4_woman": ("unknown", ["megactor__audio_CHTF_4.mp4"]),
    "megactor_entf2_woman": ("en", ["megactor__audio_ENTF_2.mp4"]),
    "mead_m003": ("en", ["spectre_mead__M003_level_1_disgusted_015.mp4"]),
    "mead_m026": ("en", ["spectre_mead__M026_level_3_disgusted_018.mp4"]),
    "mead_m030": ("en", ["spectre_mead__M030_level_3_angry_016.mp4"]),
    "mead_w023": ("en", ["spectre_mead__W023_level_2_surprised_010.mp4"]),
    "mead_w040": ("en", ["spectre_mead__W040_level_3_happy_029.mp4"]),
    # batch 2 (never seen by the shipped network)
    "donald_trump": ("en", ["mimictalk__Trump_10s.mp4"]),
    "chris_christie": ("en", ["pcavs__00015.mp4"]),
    "jamie_oliver": ("en", ["pcavs__00086.mp4"]),
    "amy_adams": ("en", ["pcavs__00373.mp4"]),
    "neil_patrick_harris": ("en", ["pcavs__681100216.mp4"]),
    "robert_downey_jr": ("en", ["pcavs__741400104.mp4", "pcavs__741400163.mp4"]),
    "lily_aldridge": ("en", ["pcavs__00002.mp4"]),
    "david_beckham": ("en", ["pcavs__00098.mp4"]),
    "patrick_stewart": ("en", ["pcavs__00473.mp4"]),
    "pcavs_796100172_man": ("en", ["pcavs__796100172.mp4"]),
    "pat_monahan": ("en", ["pcavs__681600002_av.mp4"]),
    "avcrossnet_e2_man": ("en", ["avcrossnet__E2_av.mp4"]),
    "avcrossnet_e3_woman": ("en", ["avcrossnet__E3_av.mp4"]),
    "avcrossnet_e4_man": ("en", ["avcrossnet__E4_av.mp4"]),
    "avcrossnet_e5_woman": ("en", ["avcrossnet__E5_av.mp4"]),
    "betterhelp_woman": ("en", ["cliptranslator__betterhelpgirl-english.mp4"]),
    "lrs2_glasses_man": ("en", ["deepavsr__00004.mp4", "deepavsr__00024.mp4"]),
    "lrs2_outdoor_man": ("en", ["deepavsr__00016.mp4"]),
    "lrs2_older_man": ("en", ["deepavsr__00019.mp4"]),
    "charlie_chaplin": ("en", ["nltmlipsync__dictator_orig.mp4"]),
    "shah_rukh_khan": ("hi", ["nltmlipsync__bazigar_part1.mp4"]),
    "astorfi_elderly_man": ("unknown", ["astorfilipreading__sample_video.mp4"]),
    "hdtf_news_anchor_fazsk8": ("en", ["talkingfacepreproc__FAzSK8PLmGI_crop.mp4"]),
    "mer_lab_coat_man": ("zh", ["emotionllama__sample_00000669.mp4"]),
    "mer_middle_aged_woman": ("zh", ["emotionllama__sample_00000694.mp4"]),
    "mer_older_woman": ("zh", ["emotionllama__sample_00000727.mp4"]),
    "mer_white_jacket_woman": ("zh", ["emotionllama__sample_00004136.mp4"]),
    "shawn_ashmore": ("en", ["lia__vox_driving2.mp4"]),
    "headgan_actress": ("en", ["headgan__driving.mp4"]),
    "li_bingbing": ("unknown", ["minimates__driving.mp4"]),
    "italian_lessons_man": ("it", ["multivsr__GgQ9IGGSQ0I-00003.mp4"]),
    "portuguese_lecturer": ("pt", ["multivsr__RGI2GUiiL6o-00003.mp4"]),
    "french_selfie_man": ("fr", ["multivsr__hxn8clTtMTo-00001.mp4"]),
    "voxceleb2_id00100": (
        "en",
        [
            "speakersep__id00100_0azO2YG6Bq0_00002.mp4",
            "speakersep__id00100_0azO2YG6Bq0_00003.mp4",
            "speakersep__id00100_0azO2YG6Bq0_00005.mp4",
            "speakersep__id00100_yMLqymKvTfA_00044.mp4",
            "speakersep__id00100_yMLqymKvTfA_00045.mp4",
            "speakersep__id00100_yMLqymKvTfA_00046.mp4",
            "speakersep__id00100_yMLqymKvTfA_00048.mp4",
            "speakersep__id00100_yMLqymKvTfA_00049.mp4",
            "speakersep__id00100_yMLqymKvTfA_00050.mp4",
            "speakersep__id00100_yMLqymKvTfA_00051.mp4",
        ],
    ),
    "voxceleb2_id01175": ("en", ["speakersep__id01175_ju_JcqLGBn4_00031.mp4"]),
    # added to the catalogue after batch 2
    "icable_news_anchor": ("yue", ["cantolip__icable_10075_0.mp4"]),
}


def hash_unit(person: str) -> float:
    """A fixed number in [0, 1) from the person id (rule 4)."""
    return int(hashlib.sha256(person.encode()).hexdigest()[:8], 16) / 16**8


def build() -> dict:
    manifest = json.loads((ROOT / "nvp" / "assets" / "audio2exp_phonemes.json").read_text())
    shipped = manifest["split"]
    role = {c: "train" for c in shipped["train"]} | {c: "validation" for c in shipped["validation"]}
    people = {}
    speakers = Counter(lang for lang, _ in PEOPLE.values())
    for person, (lang, clips) in PEOPLE.items():
        roles = {role[c] for c in clips if c in role}
        if len(roles) > 1:
            raise SystemExit(f"{person}: the shipped network used their clips in {sorted(roles)}")
        if roles:
            split, why = roles.pop(), "rule 2: role in the shipped network's training"
        elif any(c in shipped.get("excluded", []) for c in clips):
            raise SystemExit(f"{person}: excluded clip without a role")
        elif lang != "en" and (lang == "unknown" or speakers[lang] == 1):
            split = "test"
            alone = "language unknown" if lang == "unknown" else "the only person of their language"
            why = f"rule 3: {alone}"
        else:
            u = hash_unit(person)
            split = "test" if u < 0.5 else "validation" if u < 0.7 else "train"
            why = f"rule {4 if lang == 'en' else 3}: hash {u:.3f}"
        people[person] = {"split": split, "language": lang, "clips": clips, "why": why}
    clips = [c for p in people.values() for c in p["clips"]]
    if len(clips) != len(set(clips)):
        raise SystemExit("a clip is listed for two people")
    splits = {s: sorted(c for p in people.values() if p["split"] == s for c in p["clips"]) for s in SPLITS}
    return {
        "rule": __doc__.split("The rule (also written into the file):")[1].strip(),
        "shipped_network": "nvp/assets/audio2exp_phonemes.json (sha256 " + manifest["sha256"][:16] + ")",
        **splits,
        "people": people,
    }


SPLITS = ("train", "validation", "test")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--check", action="store_true", help="only check that the committed file is current")
    args = ap.parse_args(argv)
    data = build()
    text = json.dumps(data, indent=1, ensure_ascii=False) + "\n"
    if SHARED.is_dir():
        on_disk = {p.name for p in (SHARED / "video").glob("*.mp4")}
        listed = {c for s in SPLITS for c in data[s]}
        if on_disk != listed:
            print(f"not in the split: {sorted(on_disk - listed)}; not on disk: {sorted(listed - on_disk)}")
            return 1
    if args.check:
        ok = OUT.exists() and OUT.read_text() == text
        print("data_split.json is current" if ok else "data_split.json is out of date")
        return 0 if ok else 1
    OUT.write_text(text)
    for s in SPLITS:
        people = [p for p, v in data["people"].items() if v["split"] == s]
        langs = sorted({data["people"][p]["language"] for p in people})
        print(f"{s}: {len(people)} people, {len(data[s])} clips, languages {langs}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
