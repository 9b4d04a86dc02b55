from pathlib import Path

from setuptools import find_packages, setup

PACKAGE = "ad_sim"
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
    package_data={PACKAGE: package_files("data")},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        # XML launch files (ros2 launch ad_sim <file>): sim.launch.xml
        (f"share/{PACKAGE}/launch", sorted(str(p.relative_to(HERE)) for p in (HERE / "launch").glob("*.launch.xml"))),
    ],
    install_requires=["setuptools"],
    zip_safe=False,
    maintainer="Analytic Dynamics developers",
    maintainer_email="dev@analytic-dynamics.invalid",
    description="Warp MPM simulator of jelly, plasticine and sand: library, simulator node, recorder and bulk MCAP generator.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "node = ad_sim.sim_node:main",
            "record = ad_sim.record_node:main",
            "generate = ad_sim.generate:main",
        ],
    },
)
