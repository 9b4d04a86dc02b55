from pathlib import Path

from setuptools import find_packages, setup

PACKAGE = "ad_estimator"
HERE = Path(__file__).resolve().parent


def package_files(subdir: str) -> list[str]:
    """Every file under <package>/<subdir>, relative to the package, so files added later install too."""
    root = HERE / PACKAGE
    return sorted(
        str(path.relative_to(root))
        for path in (root / subdir).rglob("*")
        if path.is_file() and "__pycache__" not in path.parts
    )


setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*"]),
    package_data={PACKAGE: package_files("models")},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", sorted(str(p.relative_to(HERE)) for p in (HERE / "config").glob("*.yaml"))),
        # XML launch files (ros2 launch ad_estimator <file>): estimator.launch.xml, sim_estimator.launch.xml
        (f"share/{PACKAGE}/launch", sorted(str(p.relative_to(HERE)) for p in (HERE / "launch").glob("*.launch.xml"))),
    ],
    install_requires=["setuptools"],
    zip_safe=False,
    maintainer="Analytic Dynamics developers",
    maintainer_email="dev@analytic-dynamics.invalid",
    description="Online material estimation from mask videos with onnxruntime: estimator node, bag replay, offline estimation and evaluation.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "node = ad_estimator.node:main",
            "replay = ad_estimator.replay:main",
            "evaluate = ad_estimator.evaluate:main",
            "estimate = ad_estimator.estimate:main",
        ],
    },
)
